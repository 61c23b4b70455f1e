"""The base scene: find it from what the user typed, check it, and read its weights.

One function turns `--load-dir` into a checked base: the run folder (holding config.yml),
its `nerfstudio_models` folder or one `.ckpt` file are all accepted. The base's files are
only ever read.
"""

from __future__ import annotations

import re
import shlex
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import yaml

from sked_ns.engine.run_home import written_in
from sked_ns.errors import SkedFileNotFoundError, SkedUserError, check_name_lengths
from sked_ns.models.registry import family, representation_of
from sked_ns.sketches.sketch_set import DataparserTransform


@dataclass(frozen=True)
class BaseScene:
    """A trained nerfstudio run to edit (or an edit to resume)."""

    run_dir: Path
    """Folder holding config.yml."""
    checkpoint: Path
    """The latest (or chosen) step-*.ckpt."""
    config: object
    """The run's TrainerConfig, read from config.yml."""
    config_file: Optional[Path] = None
    """Where that config was read (an edit's copy of its base holds it as base_config.yml); None: run_dir's."""

    @property
    def config_path(self) -> Path:
        return self.config_file or self.run_dir / "config.yml"

    @property
    def method(self) -> str:
        return str(self.config.method_name)

    @property
    def family(self) -> str:
        """nerfacto, instant-ngp, splatfacto or sked (models/registry.py)."""
        return family(self.model_config)

    @property
    def representation(self):
        """Its registry row (models/registry.py); None for a SKED edit (an edit of any kind)."""
        return None if self.family == "sked" else representation_of(self.model_config)

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
    check_name_lengths(path, flag)  # a name too long for the file system fails exists() itself
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
        if not any(models_dir.glob("step-*.ckpt")):
            refuse_unstarted_edit(config_path)
        if not models_dir.is_dir():
            raise SkedFileNotFoundError(f"{models_dir}: missing; the run at {run_dir} has no saved checkpoints.")
        checkpoint = _latest_checkpoint(models_dir, step)
    return read_scene(run_dir, checkpoint)


def read_scene(run_dir: Path, checkpoint: Path, config_file: Optional[Path] = None) -> BaseScene:
    """The run at `run_dir` (its config.yml, or `config_file`, read and checked) with `checkpoint` as the weights it
    is loaded from."""
    config_path = config_file or run_dir / "config.yml"
    try:
        config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
        method, model_config = config.method_name, config.pipeline.model
    except Exception as error:  # yaml of nerfstudio configs imports arbitrary modules
        raise SkedUserError(f"{config_path}: cannot read this nerfstudio config ({error}).") from error
    if family(model_config) is None:
        raise SkedUserError(
            f"{config_path}: the base was trained with '{method}' ({type(model_config).__name__}); sked edits "
            "nerfacto (also -big, -huge), instant-ngp (also -bounded) and splatfacto (also -big) scenes, and its own "
            "edits."
        )
    if family(model_config) == "sked":
        warn_stale_start(config, config_path)
    return BaseScene(run_dir=run_dir, checkpoint=checkpoint, config=config, config_file=config_file)


def refuse_unstarted_edit(config_path: Path) -> None:
    """A SKED edit stopped before its first checkpoint has nothing to resume, but its settings and sketch set are
    there to start it again: say so, with the command (other runs without checkpoints get the usual message)."""
    try:
        config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
        if family(config.pipeline.model) != "sked":
            return
    except Exception:  # not readable here: the usual messages follow
        return
    original = written_in(config)  # read from a copy or a move: its checkpoints may be where it came from
    if original is not None and any((Path(original) / "nerfstudio_models").glob("step-*.ckpt")):
        raise SkedFileNotFoundError(f"{config_path.parent}: this edit folder has no checkpoints: it was copied or "
                                    f"moved without its nerfstudio_models/ from {original}. Copy "
                                    f"{Path(original) / 'nerfstudio_models'} into it to open it.")
    if original is not None:
        raise SkedFileNotFoundError(f"{config_path.parent}: this edit folder has no checkpoints: it was copied without "
                                    f"its nerfstudio_models/ (from {original}, no longer there), or the edit stopped "
                                    f"before its first checkpoint. Copy them in from where they are, or start the "
                                    f"edit again with {restart_command(config)}")
    sketches = config.pipeline.model.sketches
    saved = f" (its sketch set is saved in {sketches})" if sketches else ""
    raise SkedFileNotFoundError(f"{config_path.parent}: this edit stopped before its first checkpoint, so there is "
                                f"nothing to resume{saved}. Start it again with {restart_command(config)} (its other "
                                f"settings are in {config_path})")


def warn_stale_start(config, config_path: Path) -> None:
    """An edit resumed by an older sked_ns saved the step it resumed from as config.yml's load_step: nerfstudio's
    ns-render, ns-export and ns-viewer load that step from the run (SKED's own loaders take the latest)."""
    step = getattr(config, "load_step", None)
    if step is not None:
        warnings.warn(f"{config_path}: load_step {step} is the step its resume started from, so ns-render, ns-export "
                      "and ns-viewer load that checkpoint, or fail where the run lacks it; change the line to "
                      "`load_step: null` for the run's latest.", stacklevel=3)


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
    return f"`{shlex.join([dataparser_name(datamanager.dataparser), '--data', run_data(datamanager)])}`"


def run_data(datamanager) -> str:
    """The --data a run's config names (on the datamanager, or its dataparser's)."""
    data = getattr(datamanager, "data", None) or getattr(datamanager.dataparser, "data", None)
    return str(data) if data else "<the base data>"


def restart_command(config) -> str:
    """The `ns-train` line that starts an edit (a SKED run's TrainerConfig) again from its base, its sketch set, its
    prompt and its data, shell-quoted; further flags it was given are in its config.yml."""
    model, datamanager = config.pipeline.model, config.pipeline.datamanager
    base = Path(model.base_checkpoint).parent.parent if model.base_checkpoint else "<base run>"
    words = ["ns-train", str(config.method_name), "--load-dir", str(base)]
    if model.sketches:
        words += ["--sketches", str(model.sketches)]
    if model.prompt:
        words += ["--prompt", str(model.prompt)]
    words += guidance_words(getattr(model, "guidance", None))
    words += [dataparser_name(datamanager.dataparser), "--data", run_data(datamanager)]
    return shlex.join(words)


def guidance_words(guidance) -> list:
    """The guidance as typed: its subcommand and the settings that differ from its defaults (none for the default
    guidance at its defaults), after the plain flags and before the dataparser, as tyro reads them."""
    from dataclasses import fields

    from sked_ns.guidance import StableDiffusionGuidanceConfig, guidance_name

    if guidance is None:
        return []
    default = type(guidance)()
    flags = []
    for item in fields(guidance):
        value = getattr(guidance, item.name)
        if not item.init or item.name.startswith("_") or value == getattr(default, item.name):
            continue
        values = value if isinstance(value, (list, tuple)) else [value]
        if all(isinstance(v, (bool, int, float, str, Path)) for v in values):
            flags += [f"--pipeline.model.guidance.{item.name.replace('_', '-')}", *map(str, values)]
    if type(guidance) is StableDiffusionGuidanceConfig and not flags:
        return []
    return [f"pipeline.model.guidance:{guidance_name(guidance)}", *flags]


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
        f"{dataparser_command(base)} (see {base.config_path}, pipeline.datamanager.dataparser)."
    )


def edited_base(model) -> BaseScene:
    """An edit's base: the config, data frame and checkpoint the edit reads, from its own copy of them
    (engine/kept_base.py) once it has one, so a base run moved, deleted or trained on since does not matter."""
    from sked_ns.method.frozen_base import base_weights, kept_config

    checkpoint, weights = Path(model.base_checkpoint), base_weights(model)
    config = kept_config(weights) if weights != checkpoint else None
    if config is not None:
        return read_scene(weights.parent, weights, config_file=config)
    run = checkpoint.parent.parent  # an edit not yet started, or kept by an older sked_ns (its checkpoint alone)
    if not (run / "config.yml").exists():
        raise SkedFileNotFoundError(f"{run}: the edit's base run was moved or deleted (its config.yml is gone), and "
                                    "the edit reads the base's config and data frame from it. Put that run back "
                                    "there, or edit the base again where it is now.")
    if weights == checkpoint:
        return resolve_base(checkpoint)
    return read_scene(run, weights)
