"""The trainer of `ns-train sked`: an edit, or with no --sketches an edit session (rounds.py) in its viewer."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Optional, Type

from sked_ns.engine.drawn_sketches import no_sketches, session_sketches, sketches_pending
from sked_ns.engine.trainer import SkedTrainer, SkedTrainerConfig, resolve_edit

if TYPE_CHECKING:
    from sked_ns.session.rounds import EditSession


@dataclass
class SessionTrainerConfig(SkedTrainerConfig):
    """`ns-train sked`'s config: a SkedTrainerConfig whose trainer opens a session when --sketches is left out."""

    _target: Type = field(default_factory=lambda: SessionTrainer)

    def sketches_to_draw(self) -> None:
        """No --sketches: drawn in this run's viewer (a session), saved in its run folder."""
        if not self.is_viewer_enabled():
            raise no_sketches(self)
        self.pipeline.model.sketches = session_sketches(self)


class SessionTrainer(SkedTrainer):
    """SkedTrainer; when the sketches are to be drawn, it opens the session, trains its first round and then each
    round Edit again asks for (the later rounds' trainers are SessionTrainers of the same session)."""

    session: Optional[EditSession] = None
    """The session this trainer's round belongs to; None for an edit given --sketches."""

    def setup(self, test_mode="val") -> None:
        with self._interruptible(training=False):  # ctrl+c while the user draws: one line, status 130
            self._setup_session(test_mode)

    def _setup_session(self, test_mode: str) -> None:
        if self.session is None:
            resolve_edit(self.config)
            if sketches_pending(self.config):  # the viewer opens on the base; training waits for the sketch set
                from sked_ns.session.rounds import EditSession, abandon_unstarted  # the viewer's modules, when used

                try:
                    self.session = EditSession(self)
                    self.session.start_first_round()
                except BaseException:  # ctrl+c, or the base would not load: no run was started
                    abandon_unstarted(self.config)
                    raise
        if self.session is None:
            return super().setup(test_mode=test_mode)
        with self.session.lend_viewer(self):
            super().setup(test_mode=test_mode)

    def _show_sketches_in_viewer(self) -> None:
        if self.session is None:
            return super()._show_sketches_in_viewer()
        from sked_ns.engine.viewer import show_sketch_views

        model = self.pipeline.model  # the frusta and the edit box; the session panel lists the rounds
        show_sketch_views(self.viewer_state.viser_server, model.sketch_set.views, model.edit_box)

    def train(self) -> None:
        super().train()
        if self.session is not None and self.session.first is self:  # Edit again's rounds, in this process
            with self._interruptible(training=True):
                self.session.run_rounds(self)

    def _train_complete_viewer(self) -> None:
        if self.session is None:
            return super()._train_complete_viewer()
        self.session.round_finished(self)  # returns when the user starts another round (or the session closes)

    def train_iteration(self, step: int):
        result = super().train_iteration(step)
        if self.session is not None:
            self.session.step_done(self, step)
        return result
