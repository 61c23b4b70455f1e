"""`ns-train sked`: turns `--load-dir` into a base to edit (or an edit to resume).

nerfstudio's `--load-dir` means "resume this run": it restores the optimisers and the step.
An edit instead starts at step 0 with fresh optimisers from the base's weights, so the base
is resolved here, before the config is saved: its architecture is copied into the edit's
model config, its checkpoint recorded, and `load_dir` cleared. Pointing `--load-dir` at an
earlier SKED run resumes it from its saved config.yml (resume.py); add `--progressive True` to
edit that result again instead. Checkpoints are written so that a kill cannot leave a broken one.
"""

from __future__ import annotations

import contextlib
import copy
import pickle
import shlex
import sys
import warnings
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Optional, Type

import torch
import yaml
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.rich_utils import CONSOLE

from sked_ns.atomic import publish_atomically, write_text_atomically
from sked_ns.engine.base_scene import BaseScene, checkpoint_step, dataparser_command, resolve_base, restart_command
from sked_ns.engine.drawn_sketches import no_sketches, sketches_pending
from sked_ns.engine.edit_inputs import check_edit_inputs
from sked_ns.engine.kept_base import STORE, keep_base, keep_sketches
from sked_ns.engine.resume import preset_config, resumed_config, typed_settings
from sked_ns.engine.run_home import HOME, WRITTEN_IN, config_file_being_read, home_run_folder, rehome
from sked_ns.engine.safe_step import GuardedGradScaler, GuardedOptimizers, StepGuard, default_autocast_dtype
from sked_ns.errors import SkedFileNotFoundError, SkedUserError, check_name_lengths, check_writable_folder
from sked_ns.method.frozen_base import base_implementation
from sked_ns.method.options import SkedOptions, copy_base_architecture
from sked_ns.method.validation import check_options
from sked_ns.models.registry import representation_of
from sked_ns.progress import Heartbeat
from sked_ns.run_lock import hold, write_failure


@dataclass
class SkedTrainerConfig(TrainerConfig):
    _target: Type = field(default_factory=lambda: SkedTrainer)
    load_dir: Optional[Path] = None
    """Required: the scene to edit, a trained nerfacto, instant-ngp or splatfacto run (its folder or its
    nerfstudio_models). An earlier SKED edit here is resumed; with --progressive True its result is edited again."""
    prompt: Optional[str] = None
    """What should be in the sketched region (Stable Diffusion guidance). Leave it out to carve the region away."""
    sketches: Optional[Path] = None
    """Alias for --pipeline.model.sketches: the sketch-set folder."""
    progressive: bool = False
    """With --load-dir on an earlier SKED run: edit its result again instead of resuming it."""

    def __setstate__(self, state: dict) -> None:
        """Read from a config.yml: re-rooted at the folder it was read from (engine/run_home.py)."""
        vars(self).update(state)
        path = config_file_being_read(str(self.timestamp))
        if path is not None:
            rehome(self, path.parent)

    def get_base_dir(self) -> Path:
        return home_run_folder(self) or super().get_base_dir()

    def sketches_to_draw(self) -> None:
        """A new edit without --sketches: refused here; the session layer's config opens them in the viewer."""
        raise no_sketches(self)

    def print_to_terminal(self) -> None:
        resolve_edit(self)  # a user error before nerfstudio's config dump, not after it
        super().print_to_terminal()

    def save_config(self) -> None:
        resolve_edit(self)  # before saving, so config.yml describes the edit's real model
        # Before anything is written, not when the first checkpoint is due.
        check_writable_folder(self.get_base_dir(), "--output-dir", self.output_dir)
        # The run folder's one writer for the run's life, before config.yml or a checkpoint folder is written.
        hold(self.get_base_dir(), "Wait for it to end, or give this edit another --timestamp or --output-dir.")
        check_writable_folder(self.get_checkpoint_dir(), "--output-dir", self.output_dir)
        if sketches_pending(self):  # written with the sketch set, once the user draws it in the viewer
            return
        save_run_config(self)


def save_run_config(config: TrainerConfig) -> None:
    """config.yml as the run's later readers need it, written whole or not at all (a full disk keeps the old one).

    ns-render, ns-export and ns-viewer (nerfstudio's eval_setup) load `load_step` from the run's own checkpoints,
    and a resume's load_dir / load_step name the interrupted run's: they describe this start, not the run."""
    run_dir = config.get_base_dir()
    path = run_dir / "config.yml"
    store = (run_dir.parent if HOME in vars(config) else Path(config.output_dir)) / STORE  # shared by the edits there
    keep_base(config.pipeline.model, run_dir, store)  # the base run may replace its checkpoint later
    keep_sketches(config.pipeline.model, run_dir)  # and the sketch folder may change
    run = copy.copy(config)  # the trainer still resumes from the in-memory config
    vars(run).pop(SETTLED, None)
    for where in (HOME, WRITTEN_IN):  # where this copy of the run is now: found again whenever it is read
        vars(run).pop(where, None)
    run.load_dir = run.load_step = run.load_checkpoint = None
    CONSOLE.log(f"Saving config to: {path}")
    try:
        write_text_atomically(path, yaml.dump(run))
    except OSError as error:
        raise SkedUserError(f"{path}: cannot write the run's config ({error.strerror or error}). Free space there, "
                            "or pass another --output-dir.") from error


SETTLED = "_sked_settled_from"
"""The config's attribute recording what it was settled from (not a field: never saved in config.yml)."""


def settled_from(config: SkedTrainerConfig) -> tuple:
    """What an edit's config is resolved from: the scene and checkpoint it loads, and the aliases typed with it."""
    return (config.load_dir, config.load_step, config.load_checkpoint, config.progressive, config.sketches,
            config.prompt, config.pipeline.model.base_checkpoint)


def resolve_edit(config: SkedTrainerConfig) -> None:
    """Settle the edit's config once: nerfstudio's first hook on it (print_to_terminal under ns-train, save_config
    from Python) does the work, later ones (save_config, the trainers' setup) find it done. A config copied and
    pointed at another scene (a session's next round) is settled again."""
    if getattr(config, SETTLED, None) == settled_from(config):
        return
    _resolve_edit(config)
    object.__setattr__(config, SETTLED, settled_from(config))


def _resolve_edit(config: SkedTrainerConfig) -> None:
    """Fill the model config from --load-dir and the aliases, and check everything the edit will read."""
    check_options(config.pipeline.model, config.pipeline.datamanager)  # bad values refused before anything is written
    check_run_settings(config)
    model = config.pipeline.model
    if config.sketches is not None:
        model.sketches = config.sketches
    if config.prompt is not None:  # nerfstudio passes --prompt on only when it is not empty: "" must not carve
        model.prompt = config.prompt
    if config.load_dir is not None and config.load_checkpoint is not None:
        raise SkedUserError(f"--load-dir {config.load_dir} and --load-checkpoint {config.load_checkpoint}: give one "
                            "of them (a run folder, or one of its step-*.ckpt files).")
    # nerfstudio users also name the scene by its checkpoint file: the base, or the edit to resume, from that step.
    source, flag = (config.load_dir, "--load-dir") if config.load_checkpoint is None else (config.load_checkpoint,
                                                                                          "--load-checkpoint")
    if source is None:
        if model.base_checkpoint is None:
            raise SkedUserError("ns-train sked needs the scene to edit: --load-dir <base run>/nerfstudio_models.")
    else:
        base = resolve_base(source, config.load_step, flag=flag)
        config.load_checkpoint = None  # resume_edit sets load_dir/load_step to the checkpoint; a new edit loads none
        if base.family == "sked" and not config.progressive:
            resume_edit(config, base)
        else:
            start_edit(config, base)
            if config.pipeline.model.sketches is None:  # a new edit without --sketches
                config.sketches_to_draw()
        check_data(config, base)
    check_edit_inputs(config)  # everything the edit will read, before anything is written
    # Learning rates decay to 0.1x by the end of this edit (docs/method.md, Optimisation), however long --max-num-iterations makes it.
    for optimizer in config.optimizers.values():
        if hasattr(optimizer.get("scheduler"), "max_steps"):
            optimizer["scheduler"].max_steps = config.max_num_iterations


def check_run_settings(config: TrainerConfig) -> None:
    """The run's length and saving intervals, named by flag (nerfstudio divides by the total, so 0 would crash)."""
    total = config.max_num_iterations
    if isinstance(total, bool) or not isinstance(total, int) or total < 1:
        raise SkedUserError(f"--max-num-iterations {total!r}: an edit needs at least 1 iteration (the paper's is "
                            "10,000; sked-fast 3,000).")
    intervals = {"--steps-per-save": config.steps_per_save, "--steps-per-eval-batch": config.steps_per_eval_batch,
                 "--steps-per-eval-image": config.steps_per_eval_image,
                 "--steps-per-eval-all-images": config.steps_per_eval_all_images,
                 "--logging.steps-per-log": config.logging.steps_per_log}
    bad = [f"{name} {value!r}" for name, value in intervals.items()
           if isinstance(value, bool) or not isinstance(value, int) or value < 0]
    if bad:
        raise SkedUserError(f"{', '.join(bad)}: a number of iterations between two events, a whole number >= 0 "
                            "(0 turns the event off).")
    if config.steps_per_save == 0:
        warnings.warn("--steps-per-save 0: the edit is saved only when it ends, so a crash or kill loses all of it.",
                      stacklevel=3)


def resume_edit(config: SkedTrainerConfig, base: BaseScene) -> None:
    """Continue the interrupted edit: its saved config, the settable flags typed now, from its latest intact checkpoint."""
    resumed_config(config, base.config, preset_config(config.method_name), base.run_dir, checkpoint=base.checkpoint)
    step = checkpoint_step(base.checkpoint)
    if config.max_num_iterations <= step + 1:
        typed = "max_num_iterations" in typed_settings(config, base.config)
        raise SkedUserError(
            (f"--max-num-iterations {config.max_num_iterations}: " if typed else f"--load-dir {base.run_dir}: ")
            + f"the edit was saved after {step + 1} of its {base.config.max_num_iterations} iterations "
            f"({base.checkpoint.name}), so nothing is left to run. Pass --max-num-iterations above {step + 1} to "
            "continue it, or --progressive True to edit its result again."
        )
    config.load_dir, config.load_step = base.checkpoint.parent, step  # this checkpoint, not a newer broken one
    say_once(f"Resuming the SKED edit {base.run_dir} from {base.checkpoint.name} to {config.max_num_iterations} "
             "iterations")


def start_edit(config: SkedTrainerConfig, base: BaseScene) -> None:
    """A new edit of `base`: the model shaped like it, starting at step 0 from its weights."""
    model = config.pipeline.model = edit_model_config(config.pipeline.model, base.model_config)
    model.base_checkpoint = base.checkpoint
    model.base_kept = model.base_digest = None  # kept when config.yml is written; a copied config names another base
    if "implementation" in {f.name for f in fields(model)}:  # NeRF fields: the base's layout, not its config, decides
        model.implementation = base_implementation(base.checkpoint)
    optimizers = representation_of(base.model_config).edit_optimizers(config.max_num_iterations, model)
    if optimizers is not None:  # the presets' optimisers are a NeRF's: e.g. Gaussians take the splat edit's groups
        config.optimizers = optimizers
    config.load_dir = None  # the base is not a run to resume: fresh optimisers, step 0
    config.load_step = None
    if config.experiment_name is None:  # nerfstudio names runs after --data, which an edit gives its dataparser
        config.experiment_name = base.config.experiment_name
    say_once(f"Editing the {base.method} scene {base.run_dir} ({base.checkpoint.name})")


_SAID: set = set()


def say_once(line: str) -> None:
    """Print a line of the config's resolution once: nerfstudio's hooks resolve it more than once."""
    if line not in _SAID:
        _SAID.add(line)
        CONSOLE.print(line)


def check_data(config: TrainerConfig, base: BaseScene) -> None:
    """--data and its dataparser are given and exist (nerfstudio would look for ./transforms.json)."""
    datamanager = config.pipeline.datamanager
    data = config.data or datamanager.data or datamanager.dataparser.data
    if data is None or Path(data) == Path():
        raise SkedUserError(f"no --data: an edit reads the base's images through the base's dataparser, typed after "
                            f"every other flag: {dataparser_command(base)} (from {base.run_dir / 'config.yml'}).")
    check_name_lengths(Path(data), "--data")
    if Path(data).exists():
        return
    from sked_ns.engine.base_scene import run_data
    from sked_ns.engine.moved_data import moved_data_error

    saved = Path(run_data(base.config.pipeline.datamanager))
    if base.family == "sked" and not config.progressive and Path(data).absolute() == saved.absolute():
        raise moved_data_error(base.run_dir, Path(data), datamanager.dataparser)  # not typed: the edit's own data
    known = f" The base was trained with {dataparser_command(base)}." if saved.exists() else ""
    raise SkedFileNotFoundError(f"--data {data}: no such file or folder.{known}")


def edit_model_config(model, base_model_config):
    """The SKED model for the base's representation (Gaussians) or sampler (grid or proposals), shaped like the base,
    keeping SKED's options."""
    wanted = representation_of(base_model_config).sked_config_class()
    if not isinstance(model, wanted):
        options = {option.name: getattr(model, option.name) for option in fields(SkedOptions)}
        model = wanted(**options, eval_num_rays_per_chunk=model.eval_num_rays_per_chunk)
    copy_base_architecture(model, base_model_config)
    return model


class SkedTrainer(Trainer):
    config: SkedTrainerConfig
    skipped_steps = steps_run = 0  # of this run's steps: those skipped (a non-finite loss or gradient), all
    skipped_for: tuple = ()  # what was non-finite in the skipped steps, each named once

    def __init__(self, config: SkedTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        super().__init__(config, local_rank=local_rank, world_size=world_size)
        self.step_guard = StepGuard(lambda: self.pipeline.model.parameters())
        self.skipped_in_a_row, self._stepped = 0, False
        # Before setup, so the pipeline gets it too: never backpropagates or applies a non-finite value.
        self.grad_scaler = GuardedGradScaler(self.step_guard, enabled=self.grad_scaler.is_enabled(),
                                             device=self.device.split(":")[0])

    def setup(self, test_mode="val") -> None:
        with self._interruptible(training=False):
            self._setup(test_mode)

    def _setup(self, test_mode: str) -> None:
        resolve_edit(self.config)
        self.skipped_steps, self.steps_run, self.skipped_for = 0, 0, ()
        # fp16 on CUDA; tests set it on the CPU (where nerfstudio turns mixed precision off) to prove fp16 safety.
        self.autocast_dtype = torch.float16 if self.device.startswith("cuda") else torch.bfloat16
        super().setup(test_mode=test_mode)
        if getattr(self, "viewer_state", None) is not None:
            self._show_sketches_in_viewer()

    def _show_sketches_in_viewer(self) -> None:
        """The sketch views (frusta showing their masks) and the edit box, beside the training cameras.

        Through viser directly: nerfstudio's ViewerControl offers no scene objects (the model's controls,
        beta and the show-base / tint switches, are nerfstudio viewer elements, method/edit.py)."""
        from sked_ns.engine.viewer import frame_on_connect, show_sketch_views, training_poses

        model = self.pipeline.model
        server = self.viewer_state.viser_server
        show_sketch_views(server, model.sketch_set.views, model.edit_box)
        frame_on_connect(server, training_poses(self.pipeline), look_at=model.edit_box.center)  # the edit in view
        lines = [f"- view {i}: {v.width}x{v.height}, mask {v.mask.mean():.0%} of the image"
                 for i, v in enumerate(model.sketch_set.views)]
        with server.gui.add_folder("SKED sketches"):
            server.gui.add_markdown("\n".join(lines))

    def _load_checkpoint(self) -> None:
        if self.config.load_dir is None and self.config.load_checkpoint is None:
            # Not "training from scratch": the model already holds the base's weights.
            CONSOLE.print(f"Edit starts at step 0 from the base {self.config.pipeline.model.base_checkpoint}")
            return
        try:
            super()._load_checkpoint()
        except (EOFError, pickle.UnpicklingError, RuntimeError) as error:
            if isinstance(error, RuntimeError) and "PytorchStreamReader" not in str(error):
                raise
            path = self.config.load_checkpoint or Path(self.config.load_dir) / f"step-{self.config.load_step:09d}.ckpt"
            raise SkedUserError(f"{path}: cannot read this checkpoint ({error}). Resume from an older one with "
                                "--load-step N.") from error

    def train(self) -> None:
        # An edit's length is its total: nerfstudio 1.1.5 runs max_num_iterations more steps after a resume.
        self.config.max_num_iterations = max(self.config.max_num_iterations - self._start_step, 1)
        with self._interruptible(training=True):
            super().train()

    @contextlib.contextmanager
    def _interruptible(self, training: bool):
        """Ctrl-C: one line saying where the edit stopped and how to go on, and exit status 130 (nerfstudio's
        launch would print the traceback and exit 0, so a script could not tell an interrupted edit from a done one)."""
        try:
            yield
        except KeyboardInterrupt:
            # Plain print: rich would wrap the command and read brackets in paths or prompts as markup.
            step = getattr(self, "step", None) if training else None  # nerfstudio's loop sets it at each step
            print(interrupted_line(self.config, step), file=sys.stderr, flush=True)
            raise SystemExit(INTERRUPTED_STATUS) from None

    def setup_optimizers(self) -> GuardedOptimizers:
        return GuardedOptimizers(super().setup_optimizers(), self.step_guard)

    def train_iteration(self, step: int):
        """nerfstudio's iteration under the step guard: a non-finite loss or gradient skips the update. The first
        says that it runs, and how long it has run, until it ends (it may take minutes: the memory plan's estimate)."""
        self.step_guard.start()
        device_type = "cpu" if self.device.split(":")[0] in ("cpu", "mps") else self.device.split(":")[0]
        heartbeat = contextlib.nullcontext()
        if not self._stepped:
            what = "running the edit's first step" if step == 0 else f"running step {step}, the first since the resume"
            heartbeat, self._stepped = Heartbeat("ns-train sked", what), True
        with heartbeat, default_autocast_dtype(device_type, self.autocast_dtype):
            loss, loss_dict, metrics_dict = super().train_iteration(step)
        self.steps_run += 1
        if self.step_guard.reason == "loss":
            self._skip(step, [name for name, value in loss_dict.items() if not torch.isfinite(value).all()] or ["loss"])
        elif self.step_guard.skipped:
            self._skip(step, [self.step_guard.reason])
        else:
            self.skipped_in_a_row = 0
        metrics_dict["skipped_steps"] = torch.tensor(float(self.skipped_steps))
        return loss, loss_dict, metrics_dict

    def _skip(self, step: int, names) -> None:
        self.skipped_steps += 1
        self.skipped_in_a_row += 1
        self.skipped_for = tuple(dict.fromkeys((*self.skipped_for, *names)))
        CONSOLE.print(f"[yellow]step {step}: non-finite {', '.join(names)}; update skipped[/yellow]")
        if self.skipped_in_a_row >= MAX_SKIPPED_IN_A_ROW:
            raise SkedUserError(
                f"steps {step - self.skipped_in_a_row + 1}-{step}: every update skipped for a non-finite "
                f"{', '.join(names)}, so the edit learns nothing; stopped. {LIKELY_CAUSES}")

    @property
    def learned_nothing(self) -> bool:
        """Every step this run computed was skipped: the weights are those it started from."""
        return self.steps_run > 0 and self.skipped_steps == self.steps_run

    def _after_train(self) -> None:
        """A run that skipped every step ends as an error, not "Training Finished", and saves nothing (its weights are
        what it started from); one that skipped some says how many, before nerfstudio's panel."""
        if self.learned_nothing:
            started = "its base" if self._start_step == 0 else f"as its checkpoint of step {self._start_step - 1}"
            raise SkedUserError(
                f"{self.steps_run} of {self.steps_run} steps skipped for a non-finite {', '.join(self.skipped_for)}, "
                f"so the edit is {started}: nothing saved. {LIKELY_CAUSES}")
        if self.skipped_steps:
            CONSOLE.print(f"[yellow]{self.skipped_steps} of {self.steps_run} steps "
                          f"({self.skipped_steps / self.steps_run:.1%}) skipped for a non-finite "
                          f"{', '.join(self.skipped_for)}: their updates were not applied[/yellow]")
        # A finished edit's last checkpoint holds what it changed, not Adam's moments (twice its trainable state);
        # continuing it to more iterations starts them again. An interrupted edit's checkpoints keep them.
        for optimizer in self.optimizers.optimizers.values():
            optimizer.state.clear()
        super()._after_train()

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """Never write a checkpoint holding NaN or inf weights, nor one that a kill could leave half-written:
        nerfstudio's checkpoint is written in a staging folder beside, synced, then renamed into place."""
        bad = [name for name, p in self.pipeline.model.named_parameters() if not torch.isfinite(p).all()]
        if bad:
            CONSOLE.print(f"[red]step {step}: not saving a checkpoint with non-finite weights ({bad[:3]})[/red]")
            return
        if self.learned_nothing:  # it would hold the weights the run started from, as if trained to this step
            CONSOLE.print(f"[yellow]step {step}: not saving a checkpoint: every step so far was skipped[/yellow]")
            return
        checkpoint_dir = self.checkpoint_dir
        staging = checkpoint_dir.parent / f".{checkpoint_dir.name}.partial"  # same file system: the rename is atomic
        path = checkpoint_dir / f"step-{step:09d}.ckpt"
        try:
            self.checkpoint_dir = staging
            super().save_checkpoint(step)
            checkpoint_dir.mkdir(parents=True, exist_ok=True)
            publish_atomically(staging / path.name, path)
        except (OSError, RuntimeError) as error:
            raise write_failure(path, error, "checkpoint") from error
        finally:
            self.checkpoint_dir = checkpoint_dir
            # A save cut short (full disk, Ctrl-C) leaves no partial file to keep the disk full.
            with contextlib.suppress(OSError):
                (staging / path.name).unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                staging.rmdir()
        if self.config.save_only_latest_checkpoint:
            for older in checkpoint_dir.glob("*.ckpt"):
                if older != path:
                    older.unlink()


MAX_SKIPPED_IN_A_ROW = 32
"""Updates skipped one after another before an edit stops: an fp16 loss scale backs off from its start
(safe_step.INITIAL_LOSS_SCALE, 2**10) below 1 within 11 skips, so a longer run is not a scale being found but a
step that cannot be computed."""
LIKELY_CAUSES = ("Likely wrong: the base's weights (--load-dir: NaN or inf in its checkpoint), a learning rate "
                 "(--optimizers.<group>.optimizer.lr), or a loss weight (--pipeline.model.lambda-*, "
                 "--pipeline.model.guidance.weight) far from its default.")
INTERRUPTED_STATUS = 130
"""A shell's status for a command stopped by Ctrl-C (128 + SIGINT)."""


def interrupted_line(config: TrainerConfig, step: Optional[int]) -> str:
    """Where an interrupted edit stands: its step, its last checkpoint, and the command that goes on from it."""
    run = config.get_base_dir()
    checkpoints = sorted(config.get_checkpoint_dir().glob("step-*.ckpt"), key=checkpoint_step)
    where = "while setting up" if step is None else f"at step {step}"
    if checkpoints:
        return (f"interrupted {where}; its last checkpoint is step {checkpoint_step(checkpoints[-1])}: resume with "
                f"ns-train sked --load-dir {shlex.quote(str(run))}")
    if not (run / "config.yml").exists():
        return f"interrupted {where}, before the edit wrote anything: run the same command again to start it."
    return (f"interrupted {where}, before the edit's first checkpoint: nothing to resume. Start it again with "
            f"{restart_command(config)} (its other settings are in {run / 'config.yml'})")

