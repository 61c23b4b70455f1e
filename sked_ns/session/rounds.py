"""One viewer session from the base to an edit and back: sketch, edit, look, edit again.

`ns-train sked --load-dir BASE <dataparser>` without --sketches, with the viewer on, opens nerfstudio's viewer on
the base with the SKED session panel (`sked_ns.session.panel`), and training waits until the user draws a
sketch set and presses Start edit. Each Start edit begins a round, a nerfstudio run of its own: round 1 in the run
folder ns-train made, round k in its sibling `<timestamp>_round<k>`. A round's sketch set is saved in its folder
(`sketches/`) before its config.yml, which names it, so `ns-train sked --load-dir <round>` resumes the round and
sked-eval reads it. Round k > 1 is a progressive edit (`--progressive True`) of the round the user starts from,
the latest by default: an earlier round, or the base, goes back. The viewer outlives the rounds: each round's
trainer renders through it (`lend_viewer`).
"""

from __future__ import annotations

import contextlib
import copy
import gc
import queue
import shutil
import time
from pathlib import Path
from typing import Iterator, List, Optional

import torch
from nerfstudio.utils.rich_utils import CONSOLE

from sked_ns.drawing.sketch_viewer import CPU_PREVIEW_WIDTH, load_base, renderer
from sked_ns.drawing.sketching import SketchSession
from sked_ns.engine.drawn_sketches import session_sketches
from sked_ns.engine.edit_inputs import check_edit_inputs
from sked_ns.engine.trainer import SkedTrainer, SkedTrainerConfig, save_run_config
from sked_ns.engine.viewer import frame_on_connect, training_poses
from sked_ns.errors import SkedUserError
from sked_ns.method.edit_box import content_bounds
from sked_ns.run_lock import LOCK_NAME, hold, release
from sked_ns.session.panel import SessionPanel, StartRequest

ROUND_HOLD_HINT = "Wait for it to end, or give this edit another --timestamp or --output-dir."
PROGRESS_SECONDS = 1.0
"""The panel's step count is refreshed at most this often (each refresh is a message to every browser)."""


class SessionClosed(Exception):
    """`close` before the first Start edit: nothing to train."""


class EditSession:
    """The viewer, the session panel and the rounds; the first round's trainer drives it from ns-train's thread."""

    def __init__(self, trainer: SkedTrainer) -> None:
        from nerfstudio.viewer.viewer import Viewer as ViewerState

        config = trainer.config
        model = config.pipeline.model
        self.first = trainer
        self.timestamp = config.timestamp
        self.rounds: List[Path] = []  # round k's run folder at k - 1
        self.base = Path(model.base_checkpoint)
        self.lock = trainer.train_lock  # one lock for every round: the viewer renders under it
        datamanager = config.pipeline.datamanager
        data = datamanager.data or config.data or datamanager.dataparser.data
        _, pipeline, transform = load_base(self.base, config.machine.device_type, flag="--load-dir", data=data)
        trainer.training_state = "paused"
        self.viewer = ViewerState(config.viewer, log_filename=trainer.base_dir / config.viewer.relative_log_filename,
                                  datapath=Path(data), pipeline=pipeline, trainer=trainer, train_lock=self.lock,
                                  share=config.viewer.make_share_url)
        self.viewer.init_scene(train_dataset=pipeline.datamanager.train_dataset, train_state="paused",
                               eval_dataset=pipeline.datamanager.eval_dataset)
        self.viewer.update_scene(step=0)
        frame_on_connect(self.viewer.viser_server, training_poses(pipeline))
        self._training_buttons(False)
        bounds = content_bounds(pipeline.model.config, pipeline.model.scene_box.aabb.numpy())
        preview = CPU_PREVIEW_WIDTH if config.machine.device_type == "cpu" else None
        render = renderer(self, self.lock, preview)
        self.panel = SessionPanel(self.viewer.viser_server, lambda: SketchSession(render, transform, *bounds),
                                  prompt=model.prompt, guidance=model.guidance)
        self.panel.on_edit_again, self.panel.on_start = self._pause, self._stop_round
        self.trainer: SkedTrainer = trainer  # the round being trained
        self._installed: list = []  # the current round's model controls in the viewer
        self._last_progress = 0.0

    @property
    def model(self):
        """What the viewer shows now (the base, then the round being trained): the sketch canvases render it."""
        return self.viewer.pipeline.model

    # ---- round 1 --------------------------------------------------------------------------
    def start_first_round(self) -> None:
        """Wait for Start edit; save the set and config.yml in ns-train's run folder (refusals go back to the panel)."""
        config = self.first.config
        url = self.viewer.viewer_info[0] if self.viewer.viewer_info else "the viewer"
        CONSOLE.print(f"[bold]SKED session:[/bold] {url}. Training waits for a sketch set: draw it in the viewer's "
                      "SKED panel and press Start edit.")
        while True:
            request = self._next_request()
            try:
                self._write_sketches(config, request)
                self._checked(config, lambda: check_edit_inputs(config))
                save_run_config(config)
            except SkedUserError as error:
                self.panel.refused(str(error))
                continue
            self.first.training_state = "training"
            self._round_started(config)
            return

    # ---- rounds after the first ---------------------------------------------------------------
    def run_rounds(self, trainer: SkedTrainer) -> None:
        """After a round's training: each Edit again's round, until the user stops the process."""
        while not self.closed:
            request = self._take_request()
            if request is None:
                return
            next_trainer = self._start_round(trainer, request)
            if next_trainer is None:  # refused: the panel says why; the user fixes the set and presses Start again
                self._wait_for_request()
                continue
            release(trainer.base_dir)  # that round's run is complete: another process may resume it
            self._drop(trainer)
            trainer = next_trainer
            trainer.train()

    def round_finished(self, trainer: SkedTrainer) -> None:
        """The round's iterations are done (and saved): wait for Edit again, then Start edit (or `close`)."""
        self._training_buttons(False)
        if self.panel.requests.empty():
            self.panel.round_done(len(self.rounds), trainer.base_dir)
            CONSOLE.print("SKED session: the round is saved; Edit again in the viewer starts another (ctrl+c quits).")
        self._wait_for_request()

    def _wait_for_request(self) -> None:
        while self.panel.requests.empty() and not self.closed:
            time.sleep(0.1)

    closed: bool = False

    def close(self) -> None:
        """End the session after the round being trained (as ctrl+c does, without interrupting it)."""
        self.closed = True

    def step_done(self, trainer: SkedTrainer, step: int) -> None:
        now = time.monotonic()
        if now - self._last_progress >= PROGRESS_SECONDS:
            self._last_progress = now
            self.panel.progress(len(self.rounds), step + 1, trainer.config.max_num_iterations + trainer._start_step)

    def _start_round(self, trainer: SkedTrainer, request: StartRequest) -> Optional[SkedTrainer]:
        """Round k + 1's config, as if typed: `--load-dir <source> [--progressive True] --sketches <its folder>
        --prompt ...`, with every other setting of the round just trained; its run folder taken, set and config.yml
        written, trainer set up on the session's viewer. None when refused."""
        config: SkedTrainerConfig = copy.deepcopy(trainer.config)
        config.timestamp = f"{self.timestamp}_round{len(self.rounds) + 1}"
        source = self.base if request.source is None else self.rounds[request.source - 1]
        config.load_dir, config.load_step, config.load_checkpoint = source, None, None
        config.progressive = request.source is not None or self.first.config.progressive
        config.pipeline.model.base_checkpoint = None
        config.sketches = config.pipeline.model.sketches = session_sketches(config)
        try:
            hold(config.get_base_dir(), ROUND_HOLD_HINT)
            self._write_sketches(config, request)
            self._checked(config, config.save_config)  # resolves the round from its source, checks, writes config.yml
        except SkedUserError as error:
            abandon_unstarted(config)
            self.panel.refused(str(error))
            return None
        next_trainer = config.setup(local_rank=0, world_size=1)
        next_trainer.session = self
        next_trainer.train_lock = self.lock
        from nerfstudio.utils import writer

        writer.EVENT_WRITERS.clear()  # nerfstudio's writers are per process; this round writes its own log
        next_trainer.setup()
        self._round_started(config)
        return next_trainer

    def _write_sketches(self, config: SkedTrainerConfig, request: StartRequest) -> None:
        request.sketches.save(session_sketches(config))  # refuses a set already there (a refused one was removed)
        config.prompt = config.pipeline.model.prompt = request.prompt

    @staticmethod
    def _checked(config, check) -> None:
        """Run the edit's input checks on the saved set; a refused set is removed (it never made a round)."""
        try:
            check()
        except SkedUserError:
            shutil.rmtree(session_sketches(config), ignore_errors=True)
            raise

    def _round_started(self, config: SkedTrainerConfig) -> None:
        self.rounds.append(config.get_base_dir())
        self.panel.show_round(len(self.rounds), config.get_base_dir(), config.pipeline.model.prompt)
        CONSOLE.print(f"SKED session: round {len(self.rounds)} in {config.get_base_dir()}")

    # ---- the viewer, lent to each round's trainer -------------------------------------------------
    @contextlib.contextmanager
    def lend_viewer(self, trainer: SkedTrainer) -> Iterator[None]:
        """nerfstudio's Trainer.setup makes a viewer; a session's round gets the session's, showing its pipeline."""
        import nerfstudio.engine.trainer as nerfstudio_trainer

        def viewer_of_round(config, log_filename, datapath, pipeline, trainer, train_lock, share=False):
            self.viewer.pipeline, self.viewer.trainer, self.viewer.train_lock = pipeline, trainer, train_lock
            self._install_model_controls(pipeline)
            self._training_buttons(True)
            return self.viewer

        made = nerfstudio_trainer.ViewerState
        nerfstudio_trainer.ViewerState = viewer_of_round
        try:
            yield
        finally:
            nerfstudio_trainer.ViewerState = made
        self.trainer = trainer

    def _install_model_controls(self, pipeline) -> None:
        """The round's model controls (beta, show the base, tint) in the panel, in place of the last round's."""
        from nerfstudio.viewer.utils import parse_object
        from nerfstudio.viewer.viewer_elements import ViewerElement

        for element in self._installed:
            element.remove()
        self._installed = []
        server = self.viewer.viser_server
        for _, element in parse_object(pipeline, ViewerElement, "Custom Elements"):
            element.install(server)
            hook = element.cb_hook
            element.cb_hook = lambda element, hook=hook: [self._locked(hook, element), self.viewer._trigger_rerender()]
            self._installed.append(element)

    def _locked(self, hook, element) -> None:
        with self.lock:
            hook(element)

    def _training_buttons(self, training: bool) -> None:
        """nerfstudio's Pause / Resume buttons: hidden while nothing trains."""
        self.viewer.pause_train.visible = training
        self.viewer.resume_train.visible = False

    # ---- requests from the panel (its threads) -----------------------------------------------------
    def _pause(self) -> None:
        """Edit again while a round trains: hold it still while the user sketches."""
        trainer = self.trainer
        if self.rounds and trainer.training_state == "training":
            trainer.training_state = "paused"
            self.viewer.pause_train.visible, self.viewer.resume_train.visible = False, True

    def _stop_round(self) -> None:
        """Start edit after Edit again: the round being trained ends (nerfstudio saves it) for the next one."""
        if self.rounds:
            self.trainer.stop_training = True

    def _next_request(self) -> StartRequest:
        while not self.closed:
            with contextlib.suppress(queue.Empty):
                return self.panel.requests.get(timeout=0.1)
        raise SessionClosed("the session was closed before its first round")

    def _take_request(self) -> Optional[StartRequest]:
        with contextlib.suppress(queue.Empty):
            return self.panel.requests.get_nowait()
        return None

    @staticmethod
    def _drop(trainer: SkedTrainer) -> None:
        """The finished round's model, optimisers and guidance leave the device before the next round's steps."""
        for name in ("pipeline", "optimizers", "callbacks"):
            if hasattr(trainer, name):
                delattr(trainer, name)
        gc.collect()
        if torch.cuda.is_available():
            torch.cuda.empty_cache()


def abandon_unstarted(config: SkedTrainerConfig) -> None:
    """A round that never started (ctrl+c or an error before its config.yml): its run folder holds no run; remove what
    was put there (the lock, the viewer's log, the empty checkpoint folder), and the folder when nothing else is."""
    run = config.get_base_dir()
    if (run / "config.yml").exists():
        return
    release(run)
    for name in (LOCK_NAME, config.viewer.relative_log_filename):
        (run / name).unlink(missing_ok=True)
    # The run folder, then its method and experiment folders where the run made them and nothing else is there.
    for folder in (config.get_checkpoint_dir(), run, run.parent, run.parent.parent):
        with contextlib.suppress(OSError):  # not empty: something else is there, left alone
            folder.rmdir()
