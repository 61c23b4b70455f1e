"""An edit session (`ns-train sked` without --sketches) run on a thread of the test, as ns-train runs it."""

from __future__ import annotations

import signal
import socket
import threading
import time
from pathlib import Path


def terminal_sigint() -> None:
    """A child's SIGINT as a terminal's process has it (`Popen(preexec_fn=...)`): unblocked and at its default, whatever
    the test worker inherited or set (a blocked or ignored SIGINT is inherited through exec, and Ctrl-C would never
    arrive)."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for(condition, what: str, timeout: float = 300.0, panel=None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}" + (f"; the panel says: {panel.last_message}" if panel else ""))


def session_config(scene, output_dir: Path, sd_folder: Path, iterations: int = 4):
    """`ns-train sked --load-dir BASE --max-num-iterations N <dataparser> --data DATA`, the viewer on a free port and
    Stable Diffusion the tiny one in `sd_folder`."""
    from dataclasses import fields

    from sked_ns.engine.edit_run import edit_config
    from sked_ns.session.trainer import SessionTrainerConfig

    edit = edit_config(scene["base"], scene["data"], scene["sketches"], output_dir, iterations=iterations,
                       guidance="stable-diffusion", guidance_resolution=16, silhouette_resolution=16)
    # What `ns-train sked` builds (sked_ns.session.methods): the session layer's config class and trainer.
    config = SessionTrainerConfig(**{item.name: getattr(edit, item.name) for item in fields(edit)
                                     if item.init and item.name != "_target"})
    config.sketches = None
    config.pipeline.model.guidance.model = str(sd_folder)
    config.pipeline.model.guidance.image_size = 32
    config.vis = "viewer"
    config.viewer.websocket_port = free_port()
    config.viewer.quit_on_train_completion = False
    config.steps_per_save = 2
    return config


class SessionThread:
    """save_config, setup and train on a thread (ns-train's order); `session` once its viewer is up."""

    def __init__(self, config) -> None:
        config.set_timestamp()
        config.save_config()
        self.config, self.failure = config, []
        self.trainer = config.setup(local_rank=0, world_size=1)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        self.session = wait_for(lambda: self.trainer.session if hasattr(self.trainer.session, "panel") else
                                self._raise_failure(), "the session's viewer")

    def _run(self) -> None:
        try:
            self.trainer.setup()
            self.trainer.train()
        except BaseException as error:  # noqa: BLE001 - raised on the test's thread
            self.failure.append(error)

    def _raise_failure(self) -> None:
        if self.failure:
            raise self.failure[0]

    def wait(self, condition, what: str, timeout: float = 300.0):
        return wait_for(lambda: condition() or self._raise_failure(), what, timeout, self.session.panel)

    def close(self) -> None:
        """End the session as ctrl+c would after the round; its run folders are free for other processes then."""
        from sked_ns.drawing.sketch_viewer import stop_viewer
        from sked_ns.run_lock import release

        self.session.close()
        self.thread.join(timeout=120)
        stop_viewer(self.session.viewer)
        for folder in self.session.rounds:
            release(folder)
        assert not self.thread.is_alive(), "the session ended"
        from sked_ns.session.rounds import SessionClosed

        if self.failure and not isinstance(self.failure[0], SessionClosed):
            raise self.failure[0]
