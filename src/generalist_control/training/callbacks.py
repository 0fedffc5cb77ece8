"""The training's callbacks: those named in ``callbacks``, DAgger and the closed-loop score."""

from __future__ import annotations

import logging
from typing import Any, cast

import lightning as L
import numpy as np
import torch

from generalist_control.data.windows import Windows
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import Plant
from generalist_control.plants.variants import make_variant
from generalist_control.simulation.comparison import ClosedLoopScore
from generalist_control.training.datamodule import WindowTensors
from generalist_control.training.labeller import ExpertLabeller
from generalist_control.training.sampler import RolloutSampler
from generalist_control.training.settings import DaggerSettings
from generalist_control.training.unseen_draw import UnseenDraw

__all__ = [
    "ClosedLoopValidation",
    "DAggerCallback",
    "dagger_plants",
    "dagger_round",
]

log = logging.getLogger(__name__)


class ClosedLoopValidation(L.Callback):
    """Log ``val/closed_loop`` after each validation: the mean of ``score`` over its plants.

    Open-loop MSE says little about the closed loop (a small feedback error on an unstable
    plant diverges), so DAgger's best checkpoint is chosen on this. Per plant (or label):
    ``val/closed_loop/<plant>``. With ``unseen`` (a draw and its score), the draw's plants
    join the mean, met zero-shot as at deployment; their own mean is ``val/closed_loop/unseen``.
    """

    def __init__(
        self, score: ClosedLoopScore, unseen: tuple[UnseenDraw, ClosedLoopScore] | None = None
    ) -> None:
        self.score, self.unseen = score, unseen

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Score the current policy in closed loop and log it."""
        if trainer.sanity_checking or not (self.score.runs or self.unseen):
            return
        policy = cast(Policy, pl_module.policy)
        was_training = policy.training
        meta = cast(Any, trainer).datamodule.meta()
        scores: dict[str, float] = {}
        with torch.inference_mode():
            if self.score.runs:
                scores = self.score(RuntimeAdapter(PolicyRuntime(policy, meta)))
            if self.unseen:
                draw, score = self.unseen
                unseen = score(RuntimeAdapter(PolicyRuntime(*draw.met(policy, meta))))
                pl_module.log("val/closed_loop/unseen", float(np.mean(list(unseen.values()))),
                              logger=False)  # fmt: skip
                scores.update(unseen)
        policy.train(was_training)
        pl_module.log("val/closed_loop", float(np.mean(list(scores.values()))), prog_bar=True,
                      logger=False)  # fmt: skip
        for name, v in scores.items():
            pl_module.log(f"val/closed_loop/{name}", v, logger=False)


class DAggerCallback(L.Callback):
    """DAgger (ours): expert-labelled rollouts of the policy join the training set.

    After epoch ``start_epoch``, then every ``every`` epochs, for ``rounds`` rounds; validation
    stays on the demonstrations. ``history`` holds each round's record; early stopping's
    patience restarts after each round (the training set has changed).
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
        windows, counts = dagger_round(
            self.sampler, self.labeller, runtime, dm.train_set, self.done, beta
        )
        policy.train(was_training)
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


def dagger_round(
    sampler: RolloutSampler,
    labeller: ExpertLabeller,
    runtime: PolicyRuntime,
    train_set: WindowTensors,
    round_index: int,
    beta: float,
) -> tuple[Windows, dict[str, int]]:
    """Roll ``runtime``'s policy out, label what it visits, add it to ``train_set``."""
    with torch.inference_mode():
        rollouts = sampler.run(round_index, runtime, beta)
        bounds = labeller.bounds(train_set, rollouts.plants)
        windows, counts = labeller.label(rollouts, bounds)
    train_set.append(windows)
    return windows, counts


def dagger_plants(plants: list[Plant], manifest: dict[str, Any]) -> list[Plant]:
    """``plants`` and the data's variants of them, rebuilt from the manifest's factors."""
    recorded = manifest.get("variants") or {}
    out: list[Plant] = []
    for p in plants:
        out.append(p)
        out.extend(make_variant(p, v["factors"]) for v in recorded.get(p.name, {}).get("kept", []))
    return out
