"""Training callbacks of ours: the closed-loop validation score ``val/closed_loop``."""

from __future__ import annotations

from typing import Any, cast

import lightning as L
import numpy as np
import torch

from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.simulation.comparison import ClosedLoopScore

__all__ = ["ClosedLoopValidation"]


class ClosedLoopValidation(L.Callback):
    """Log ``val/closed_loop`` after each validation: the mean :func:`closed_loop_score`.

    Open-loop validation MSE says little about the closed loop (a small error in the
    feedback of an unstable plant diverges), so with DAgger the best checkpoint is chosen
    on this score (``monitor: val/closed_loop``). Per plant: ``val/closed_loop/<plant>``, or
    per label where the score's ``labels`` name the plants (e.g. ``<plant>/v<index>`` for a
    variant). ``score``: the plants and steps (:class:`ClosedLoopScore`).
    The mean is shown in the progress bar too (3 significant digits, see
    :meth:`~generalist_control.training.lit_module.ImitationModule.setup`).
    """

    def __init__(self, score: ClosedLoopScore) -> None:
        self.score = score  # LQI's responses are simulated once, at the first validation

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Score the current policy in closed loop and log it."""
        if trainer.sanity_checking or not self.score.runs:
            return
        policy = cast(Policy, pl_module.policy)
        was_training = policy.training
        runtime = PolicyRuntime(policy, cast(Any, trainer).datamodule.meta())
        with torch.inference_mode():
            scores = self.score(RuntimeAdapter(runtime))
        policy.train(was_training)
        score = float(np.mean(list(scores.values())))
        pl_module.log("val/closed_loop", score, prog_bar=True, logger=False)
        for name, v in scores.items():
            pl_module.log(f"val/closed_loop/{name}", v, logger=False)
