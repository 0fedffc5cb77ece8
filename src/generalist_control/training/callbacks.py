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
    """Log ``val/closed_loop`` after each validation: the mean of ``score`` over its plants.

    Open-loop MSE says little about the closed loop (a small feedback error on an unstable
    plant diverges), so DAgger's best checkpoint is chosen on this. Per plant (or label):
    ``val/closed_loop/<plant>``.
    """

    def __init__(self, score: ClosedLoopScore) -> None:
        self.score = score

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
