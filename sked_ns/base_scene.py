"""The base scene: find it from what the user typed, check it, and read its weights.

One function turns `--load-dir` into a checked base: the run folder (holding config.yml),
its `nerfstudio_models` folder or one `.ckpt` file are all accepted. The base's files are
only ever read.
"""

from __future__ import annotations

import copy
import re
import warnings
import zipfile
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch
import yaml
from nerfstudio.models.instant_ngp import InstantNGPModelConfig
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.models.splatfacto import SplatfactoModelConfig
from torch import Tensor

from sked_ns.errors import SkedFileNotFoundError, SkedUserError
from sked_ns.options import SkedOptions
from sked_ns.sketches import DataparserTransform

# What the edit decides, not the base; every other field of the base's model config is copied (its architecture).
EDIT_OWNED_FIELDS = frozenset({
    "_target",  # the SKED model class
    "prompt",  # nerfstudio's ModelConfig has one too: the edit's prompt is SKED's
    "eval_num_rays_per_chunk",  # a rendering setting of this run
    # the edit's own losses
    "loss_coefficients", "interlevel_loss_mult", "distortion_loss_mult", "orientation_loss_mult", "pred_normal_loss_mult",
    # schedules of training from scratch: an edit starts from trained proposals (its anneal stays 1)
    "proposal_update_every", "proposal_warmup", "use_proposal_weight_anneal", "proposal_weights_anneal_slope",
    "proposal_weights_anneal_max_num_iters",
    "camera_optimizer",  # the edit keeps the base's cameras; the base's mode goes to base_camera_optimizer
    "edit_box_density", "grid_update_interval",  # SKED's sampling of the edit box
    # splatfacto: the edit's seeds and kept set, and schedules of training from scratch (an edit starts from a
    # trained base, at full resolution and SH degree, without opacity resets)
    "keep_threshold", "num_seeds", "seed_opacity", "seed_size", "reset_alpha_every", "warmup_length", "refine_every",
    "stop_split_at", "stop_screen_size_at", "sh_degree_interval", "resolution_schedule", "num_downscales",
    "random_init", "num_random", "random_scale",
})


def base_family(model_config) -> Optional[str]:
    """nerfacto, instant-ngp, splatfacto or sked (an earlier edit), by the config's type: nerfacto-big and -huge
    runs save method_name "nerfacto", splatfacto-big "splatfacto", and any nerfacto- or instant-ngp-style config has
    the field SKED edits."""
    if isinstance(model_config, SkedOptions):
        return "sked"
    if isinstance(model_config, SplatfactoModelConfig):
        return "splatfacto"
    if isinstance(model_config, InstantNGPModelConfig):
        return "instant-ngp"
    if isinstance(model_config, NerfactoModelConfig):
        return "nerfacto"
    return None


def copy_base_architecture(target, base_model_config) -> None:
    """Make the edit's model the base's shape: every field of the base's model config but the edit's own."""
    owned = EDIT_OWNED_FIELDS | {option.name for option in fields(SkedOptions)}
    ours = {f.name for f in fields(target)}
    for name in (f.name for f in fields(base_model_config)):
        if name in ours and name not in owned:
            setattr(target, name, copy.deepcopy(getattr(base_model_config, name)))
    cameras = getattr(base_model_config, "camera_optimizer", None)
    target.base_camera_optimizer = getattr(cameras, "mode", "off") if cameras is not None else "off"


@dataclass(frozen=True)
class BaseScene:
    """A trained nerfstudio run to edit (or an edit to resume)."""

    run_dir: Path
    """Folder holding config.yml."""
    checkpoint: Path
    """The latest (or chosen) step-*.ckpt."""
    config: object
    """The run's TrainerConfig, read from config.yml."""

    @property
    def method(self) -> str:
        return str(self.config.method_name)

    @property
    def family(self) -> str:
        """nerfacto, instant-ngp or sked."""
        return base_family(self.model_config)

    @property
    def model_config(self):
        return self.config.pipeline.model


def checkpoint_step(checkpoint: Path) -> int:
    """The step in a nerfstudio checkpoint's name (step-000000020.ckpt)."""
    return int(checkpoint.stem.split("-")[1])


def checkpoint_damage(checkpoint: Path) -> Optional[str]:
    """Why a checkpoint cannot be read, or None: a file cut short by a kill is empty or lacks the zip index
    that torch.save writes last. Reads the file once (CRCs), without unpickling it."""
    try:
        if checkpoint.stat().st_size == 0:
            return "it is empty (0 bytes)"
        with open(checkpoint, "rb") as file:
            if file.read(4) != b"PK\x03\x04":  # not torch's zip format: torch.load judges it
                return None
        with zipfile.ZipFile(checkpoint) as archive:
            corrupt = archive.testzip()
    except (OSError, zipfile.BadZipFile, EOFError) as error:
        return f"it is truncated or unreadable ({error})"
    return f"its entry {corrupt} is corrupt" if corrupt else None


def _latest_checkpoint(models_dir: Path, step: Optional[int]) -> Path:
    """The checkpoint of --load-step, else the latest intact one: a broken newer one is named and skipped."""
    checkpoints = sorted(models_dir.glob("step-*.ckpt"), key=checkpoint_step, reverse=True)
    if not checkpoints:
        raise SkedFileNotFoundError(f"{models_dir}: no step-*.ckpt checkpoint here. Point --load-dir at a trained run.")
    if step is not None:
        chosen = models_dir / f"step-{step:09d}.ckpt"
        if not chosen.exists():
            raise SkedFileNotFoundError(f"{chosen}: no checkpoint for --load-step {step}.")
        damage = checkpoint_damage(chosen)
        if damage:
            raise SkedUserError(f"{chosen}: cannot use this checkpoint: {damage}. Leave out --load-step for the "
                                "latest intact one.")
        return chosen
    for checkpoint in checkpoints:
        damage = checkpoint_damage(checkpoint)
        if damage is None:
            return checkpoint
        # A kill while saving (a run older than atomic checkpoints, or a full disk) leaves the last one cut short.
        warnings.warn(f"{checkpoint}: skipped, {damage}; using an older checkpoint.", stacklevel=3)
    raise SkedUserError(f"{models_dir}: every checkpoint here is broken (empty or truncated); nothing to load.")


def resolve_base(load_dir: Path, step: Optional[int] = None, flag: str = "--load-dir") -> BaseScene:
    """Accept `<run>`, `<run>/nerfstudio_models` or a `.ckpt` file; read and check config.yml. `flag` names the
    option the path came from in errors."""
    path = Path(load_dir).expanduser()
    if not path.exists():
        raise SkedFileNotFoundError(f"{flag} {path}: no such file or folder.")
    if path.is_file():
        if not re.fullmatch(r"step-\d+\.ckpt", path.name):
            raise SkedUserError(f"{flag} {path}: not a nerfstudio checkpoint (step-NNNNNNNNN.ckpt in a run's "
                                "nerfstudio_models folder); give the run folder or one of its checkpoints.")
        if step is not None and checkpoint_step(path) != step:
            raise SkedUserError(f"{flag} {path} and --load-step {step}: they name different checkpoints; give one.")
        models_dir, checkpoint = path.parent, path
    elif (path / "config.yml").exists():
        models_dir, checkpoint = path / "nerfstudio_models", None
    else:
        models_dir, checkpoint = path, None
    run_dir = models_dir.parent
    config_path = run_dir / "config.yml"
    if not config_path.exists():
        raise SkedFileNotFoundError(
            f"{config_path}: missing. {flag} must be a nerfstudio run folder (with config.yml) or its "
            "nerfstudio_models folder; the base's config.yml says which model it is."
        )
    if checkpoint is None:
        if not models_dir.is_dir():
            raise SkedFileNotFoundError(f"{models_dir}: missing; the run at {run_dir} has no saved checkpoints.")
        checkpoint = _latest_checkpoint(models_dir, step)
    try:
        config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
        method, model_config = config.method_name, config.pipeline.model
    except Exception as error:  # yaml of nerfstudio configs imports arbitrary modules
        raise SkedUserError(f"{config_path}: cannot read this nerfstudio config ({error}).") from error
    if base_family(model_config) is None:
        raise SkedUserError(
            f"{config_path}: the base was trained with '{method}' ({type(model_config).__name__}); sked edits "
            "nerfacto (also -big, -huge), instant-ngp (also -bounded) and splatfacto (also -big) scenes, and its own "
            "edits."
        )
    if base_family(model_config) == "sked":
        warn_stale_start(config, config_path)
    return BaseScene(run_dir=run_dir, checkpoint=checkpoint, config=config)


def warn_stale_start(config, config_path: Path) -> None:
    """An edit resumed by an older sked_ns saved the step it resumed from as config.yml's load_step: nerfstudio's
    ns-render, ns-export and ns-viewer load that step from the run (SKED's own loaders take the latest)."""
    step = getattr(config, "load_step", None)
    if step is not None:
        warnings.warn(f"{config_path}: load_step {step} is the step its resume started from, so ns-render, ns-export "
                      "and ns-viewer load that checkpoint, or fail where the run lacks it; change the line to "
                      "`load_step: null` for the run's latest.", stacklevel=3)


def read_model_state(checkpoint: Path) -> Dict[str, Tensor]:
    """The model's weights from a nerfstudio checkpoint, keys without the `_model.` prefix."""
    import sked_ns.compat  # noqa: F401  (numpy scalars in nerfstudio checkpoints)

    try:
        state = torch.load(checkpoint, map_location="cpu")
        pipeline = state["pipeline"]
    except Exception as error:
        raise SkedUserError(f"{checkpoint}: not a readable nerfstudio checkpoint ({error}).") from error
    prefix = "_model."
    model_state = {}
    for key, value in pipeline.items():
        key = key[len("module.") :] if key.startswith("module.") else key
        if key.startswith(prefix):
            model_state[key[len(prefix) :]] = value
    if not model_state:
        raise SkedUserError(f"{checkpoint}: holds no model weights (no '_model.' keys).")
    return model_state


def uses_tcnn(state: Dict[str, Tensor], prefix: str = "field.") -> bool:
    """tiny-cuda-nn modules store one flat `params` tensor; the torch ones named layers."""
    return any(key.startswith(prefix) and key.endswith(".params") for key in state)


def dataparser_name(dataparser_config) -> str:
    """The `ns-train` subcommand of a dataparser config (e.g. instant-ngp-data), or its class name."""
    from nerfstudio.configs.dataparser_configs import all_dataparsers

    for name, config in all_dataparsers.items():
        if type(config) is type(dataparser_config):
            return name
    return type(dataparser_config).__name__


def dataparser_command(base: BaseScene) -> str:
    """The dataparser subcommand and --data the base was trained with, as the user types them."""
    datamanager = base.config.pipeline.datamanager
    dataparser = datamanager.dataparser
    data = getattr(datamanager, "data", None) or getattr(dataparser, "data", None) or "<the base data>"
    return f"`{dataparser_name(dataparser)} --data {data}`"


def check_same_frame(base: BaseScene, here: DataparserTransform) -> None:
    """The edit's --data and dataparser must put the scene where the base's field has it: another
    orientation, centring or scale would query the base at the wrong points, silently."""
    path = base.run_dir / "dataparser_transforms.json"
    if not path.exists():  # nerfstudio writes it for every run; without it there is nothing to compare
        warnings.warn(f"{path}: missing, so the frame of --data and its dataparser cannot be checked against the "
                      f"base's; make sure they are the base's own: {dataparser_command(base)}.", stacklevel=2)
        return
    saved = DataparserTransform.from_json(path)
    if np.allclose(saved.transform, here.transform, atol=1e-5) and abs(saved.scale - here.scale) <= 1e-5 * saved.scale:
        return
    raise SkedUserError(
        f"{path}: the base was trained in another frame than --data and its dataparser give here (base scale "
        f"{saved.scale:.6g}, translation {np.round(saved.transform[:, 3], 4).tolist()}; here scale {here.scale:.6g}, "
        f"translation {np.round(here.transform[:, 3], 4).tolist()}). Pass the base's dataparser and its settings: "
        f"{dataparser_command(base)} (see {base.run_dir / 'config.yml'}, pipeline.datamanager.dataparser)."
    )
