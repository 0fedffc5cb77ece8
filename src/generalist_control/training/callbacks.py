"""Training callbacks of ours: the closed-loop validation score ``val/closed_loop``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, cast

import lightning as L
import numpy as np
import torch

from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.plant import Plant
from generalist_control.simulation.comparison import closed_loop_score

__all__ = ["ClosedLoopValidation"]


class ClosedLoopValidation(L.Callback):
    """Log ``val/closed_loop`` after each validation: the mean :func:`closed_loop_score`.

    Open-loop validation MSE says little about the closed loop (a small error in the
    feedback of an unstable plant diverges), so with DAgger the best checkpoint is chosen
    on this score (``monitor: val/closed_loop``). Per plant: ``val/closed_loop/<plant>``, or
    per label where ``labels`` name the plants (e.g. ``<plant>/v<index>`` for a variant).
    The mean is shown in the progress bar too (3 significant digits, see
    :meth:`~generalist_control.training.lit_module.ImitationModule.setup`).
    """

    def __init__(
        self,
        plants: Sequence[Plant],
        amplitudes: Sequence[float] = (1.0, -3.0),
        duration: float = 10.0,
        labels: Sequence[str] | None = None,
    ) -> None:
        self.plants, self.amplitudes, self.duration = list(plants), amplitudes, duration
        self.labels = None if labels is None else list(labels)

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Score the current policy in closed loop and log it."""
        if trainer.sanity_checking or not self.plants:
            return
        policy = cast(Policy, pl_module.policy)
        was_training = policy.training
        runtime = PolicyRuntime(policy, cast(Any, trainer).datamodule.meta())
        with torch.inference_mode():
            scores = closed_loop_score(
                RuntimeAdapter(runtime), self.plants, self.amplitudes, self.duration, self.labels
            )
        policy.train(was_training)
        score = float(np.mean(list(scores.values())))
        pl_module.log("val/closed_loop", score, prog_bar=True, logger=False)
        for name, v in scores.items():
            pl_module.log(f"val/closed_loop/{name}", v, logger=False)
