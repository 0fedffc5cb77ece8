"""DAgger during training (ours, not the paper's): a thin callback around a sampler and a labeller.

After epoch ``start_epoch``, then every ``every`` epochs, for ``rounds`` rounds, the sampler
rolls the policy out, the labeller labels the visited states with the experts' plans, and
the windows join the training set (validation stays on the demonstrations).
"""

from __future__ import annotations

import logging
from typing import Any, cast

import lightning as L
import torch

from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.training.labeller import ExpertLabeller
from generalist_control.training.sampler import RolloutSampler
from generalist_control.training.settings import DaggerSettings

__all__ = ["DAggerCallback"]

log = logging.getLogger(__name__)


class DAggerCallback(L.Callback):
    """Aggregate expert-labelled policy rollouts into the training set during training.

    ``history`` holds per round its number, ``beta``, the windows added and kept per plant.
    Early stopping's patience restarts after each round: the training set has changed.
    """

    def __init__(
        self, sampler: RolloutSampler, labeller: ExpertLabeller, settings: DaggerSettings
    ) -> None:
        self.sampler, self.labeller, self.settings = sampler, labeller, settings
        self.done = 0
        self.history: list[dict[str, Any]] = []

    def due(self, epochs_done: int) -> bool:
        """Whether a round runs after ``epochs_done`` finished epochs."""
        s = self.settings
        if self.done >= s.rounds or epochs_done < s.start_epoch:
            return False
        return (epochs_done - s.start_epoch) % s.every == 0

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Run a round when one is due; append its windows to the training set."""
        if not self.due(trainer.current_epoch + 1):
            return
        dm = cast(Any, trainer).datamodule
        beta = self.settings.beta_at(self.done)
        policy = cast(Policy, pl_module.policy)
        was_training = policy.training
        runtime = PolicyRuntime(policy, dm.meta())
        with torch.inference_mode():
            rollouts = self.sampler.run(self.done, runtime, beta)
            bounds = self.labeller.bounds(dm.train_set, rollouts.plants)
            windows, counts = self.labeller.label(rollouts, bounds)
        policy.train(was_training)
        dm.train_set.append(windows)
        self.done += 1
        for cb in cast(Any, trainer).callbacks:  # the training set changed: patience anew
            if isinstance(cb, L.pytorch.callbacks.EarlyStopping):
                cb.wait_count = 0
        trainer.should_stop = False
        record = {"round": self.done, "beta": beta, "windows": len(windows), **counts}
        self.history.append(record)
        log.info("DAgger round %d (beta %.3g): %d windows added", self.done, beta, len(windows))
        pl_module.log("dagger/windows", float(len(windows)), logger=False)
        pl_module.log("dagger/beta", float(beta), logger=False)
