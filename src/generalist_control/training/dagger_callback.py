"""The DAgger rounds during training: a Lightning callback around :func:`aggregate`."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any, cast

import lightning as L
import numpy as np
import torch

from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.plant import Plant
from generalist_control.training.dagger import aggregate

__all__ = ["DAggerCallback"]

log = logging.getLogger(__name__)


class DAggerCallback(L.Callback):
    """Aggregate expert-labelled policy rollouts into the training set during training.

    After epoch ``start_epoch`` and then every ``every`` epochs, for ``rounds`` rounds:
    roll the current policy out on every training plant (``rollouts`` steps per plant
    from rest, amplitudes drawn uniformly within the plant's data range), label the
    visited states with :func:`expert_plans`, and append the windows to the data module's
    training set. The trainer must reload its dataloaders every epoch
    (``reload_dataloaders_every_n_epochs=1``; :func:`generalist_control.training.fit.train` sets
    it). Validation stays on the expert demonstrations. After each round, early stopping's
    patience starts again (the training set has changed).

    Parameters
    ----------
    plants : sequence of Plant
        The training plants.
    limit : float
        Largest step amplitude before each plant's ``amplitude_scale``.
    start_epoch, every, rounds, rollouts, duration : int / float
    beta, beta_decay : float
        Expert weight in round ``i``: ``beta * beta_decay ** i``.
    bound_factor : float
        Rollouts are cut where a state exceeds ``bound_factor`` times the largest magnitude
        that state reaches in the training demonstrations.
    seed : int
    """

    def __init__(
        self,
        plants: Sequence[Plant],
        limit: float = 20.0,
        start_epoch: int = 10,
        every: int = 5,
        rounds: int = 4,
        rollouts: int = 8,
        duration: float = 10.0,
        beta: float = 0.5,
        beta_decay: float = 0.5,
        bound_factor: float = 3.0,
        takeover: str = "auto",
        seed: int = 0,
    ) -> None:
        self.plants = list(plants)
        self.limit, self.start_epoch, self.every = float(limit), int(start_epoch), int(every)
        self.rounds, self.rollouts, self.duration = int(rounds), int(rollouts), float(duration)
        self.beta, self.beta_decay = float(beta), float(beta_decay)
        self.bound_factor, self.seed = float(bound_factor), int(seed)
        if takeover not in ("auto", "bumpless", "tracked"):
            raise ValueError(
                f"dagger.takeover must be 'auto', 'bumpless' or 'tracked', got {takeover!r}"
            )
        self.takeover = takeover
        self.done = 0
        self.history: list[dict[str, Any]] = []

    def _due(self, epochs_done: int) -> bool:
        if self.done >= self.rounds or epochs_done < self.start_epoch:
            return False
        return (epochs_done - self.start_epoch) % self.every == 0

    def _bounds(self, train_set: Any) -> dict[str, np.ndarray]:
        t = train_set.tensors
        out = {}
        for p in self.plants:
            sel = t["tag"] == p.tag
            peak = t["state"][sel][..., : p.order].abs().amax(dim=(0, 1)).double().numpy()
            out[p.name] = self.bound_factor * np.maximum(peak, 1e-9)
        return out

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Run a round when one is due; append its windows to the training set."""
        if not self._due(trainer.current_epoch + 1):
            return
        dm = cast(Any, trainer).datamodule
        rng = np.random.default_rng(self.seed + self.done)
        amps = {
            p.name: rng.uniform(-self.limit, self.limit, self.rollouts) * p.amplitude_scale
            for p in self.plants
        }
        steps = int(round(self.duration / self.plants[0].dt))
        beta = self.beta * self.beta_decay**self.done
        policy = cast(Policy, pl_module.policy)
        was_training = policy.training
        runtime = PolicyRuntime(policy, dm.meta())
        integral = runtime.integral
        takeover = self.takeover
        if takeover == "auto":
            takeover = "tracked" if integral else "bumpless"
        with torch.inference_mode():
            windows, counts = aggregate(
                self.plants, runtime, beta, amps, self._bounds(dm.train_set), steps,
                dm.history, dm.horizon, takeover, integral,
            )  # fmt: skip
        policy.train(was_training)
        dm.train_set.append(windows)
        self.done += 1
        # The training set changed: early stopping's patience starts again from here.
        for cb in cast(Any, trainer).callbacks:
            if isinstance(cb, L.pytorch.callbacks.EarlyStopping):
                cb.wait_count = 0
        trainer.should_stop = False
        record = {"round": self.done, "beta": beta, "windows": len(windows), **counts}
        self.history.append(record)
        log.info("DAgger round %d (beta %.3g): %d windows added", self.done, beta, len(windows))
        for key in ("windows", "beta"):
            pl_module.log(f"dagger/{key}", float(record[key]), logger=False)
