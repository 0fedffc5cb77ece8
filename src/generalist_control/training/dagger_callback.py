"""The DAgger rounds during training: a Lightning callback around :func:`aggregate`."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any, cast

import lightning as L
import numpy as np
import torch

from generalist_control.common.schema import require_int
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.plant import Plant
from generalist_control.plants.variants import DEFAULT_RANGE
from generalist_control.simulation.references import family_references
from generalist_control.simulation.variants import sample_variants
from generalist_control.training.dagger import RolloutSpec, aggregate

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
    families : mapping, optional
        The data's demonstration families (``data.families``, enabled ones): each round
        also rolls out ``family_count`` references of each family per plant, drawn with a
        seed of its own (:func:`~generalist_control.simulation.references.family_references`),
        from the family's random initial states.
    family_count : int
    focus, focus_beta : float
        Lost-plant focus (0: off). A plant whose latest closed-loop validation score
        (``val/closed_loop/<plant>``, 0 for matching its expert, 1 for diverging or holding
        still; :class:`~generalist_control.training.callbacks.ClosedLoopValidation`) is ``s``
        gets ``round(focus * s * rollouts)`` more step rollouts in the round, and an expert
        share of at least ``focus_beta * s`` in them, so a plant the policy still loses is
        rolled out more often and stays in range longer while the expert steers it. Needs the
        closed-loop validation; a plant without a score counts as ``s = 0``.
    variants : int, optional
        With plant variants among ``plants`` (versions sharing a plant's name, the nominal
        one first), roll out on each plant's nominal version and only this many of its
        variants per round, taken in turn (round ``i``: variants ``i*k+1 .. i*k+k``, wrapping
        around), so that many variants keep the round's cost. None: every version.
    fresh_variants : int
        Each round also rolls out on this many variants of each plant drawn for that round
        alone (:func:`~generalist_control.simulation.variants.sample_variants`: fit for LQI,
        steps of +-``limit`` included; seed ``variant_seed + round``, parameters within
        ``variant_range``, at most ``variant_tries`` draws per variant), each labelled by
        its own LQI expert, so the policy learns to recover on many more variants than the
        data holds. 0: off. Their factors are kept in :attr:`fresh`, per plant.
    variant_seed, variant_range, variant_tries : int / float / int
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
        families: Mapping[str, Mapping[str, Any]] | None = None,
        family_count: int = 2,
        focus: float = 0.0,
        focus_beta: float = 0.0,
        variants: int | None = None,
        fresh_variants: int = 0,
        variant_seed: int = 3001,
        variant_range: float = DEFAULT_RANGE,
        variant_tries: int = 10,
    ) -> None:
        self.plants = list(plants)
        if variants is not None:
            variants = require_int("dagger.variants", variants, minimum=0)
        self.variants = variants
        self.fresh_variants = require_int("dagger.fresh_variants", fresh_variants, minimum=0)
        self.variant_seed = require_int("dagger.variant_seed", variant_seed, minimum=0)
        self.variant_range = float(variant_range)
        self.variant_tries = require_int("dagger.variant_tries", variant_tries, minimum=1)
        self.fresh: dict[str, list[dict[str, float]]] = {}
        self.limit, self.start_epoch, self.every = float(limit), int(start_epoch), int(every)
        self.rounds, self.rollouts, self.duration = int(rounds), int(rollouts), float(duration)
        self.beta, self.beta_decay = float(beta), float(beta_decay)
        self.bound_factor, self.seed = float(bound_factor), int(seed)
        if takeover not in ("auto", "bumpless", "tracked"):
            raise ValueError(
                f"dagger.takeover must be 'auto', 'bumpless' or 'tracked', got {takeover!r}"
            )
        self.takeover = takeover
        self.families = {k: dict(v) for k, v in (families or {}).items()}
        self.family_count = int(family_count)
        self.focus, self.focus_beta = float(focus), float(focus_beta)
        if self.focus < 0 or not 0 <= self.focus_beta <= 1:
            raise ValueError(
                f"dagger.focus must be >= 0 and dagger.focus_beta in [0, 1], "
                f"got {focus!r} and {focus_beta!r}"
            )
        self.done = 0
        self.history: list[dict[str, Any]] = []

    def _versions(self) -> list[list[Plant]]:
        """The plants grouped by name, each group its nominal version first."""
        groups: dict[str, list[Plant]] = {}
        for p in self.plants:
            groups.setdefault(p.name, []).append(p)
        return list(groups.values())

    def _round_plants(self) -> list[Plant]:
        """The round's plants: all, or each nominal version and ``variants`` in turn."""
        if self.variants is None:
            return self.plants
        out = []
        for nominal, *rest in self._versions():
            k = min(self.variants, len(rest))
            out.append(nominal)
            out.extend(rest[(self.done * k + j) % len(rest)] for j in range(k))
        return out

    def _fresh_plants(self, steps: int) -> list[Plant]:
        """The round's fresh variants: ``fresh_variants`` per plant, drawn for this round."""
        if not self.fresh_variants:
            return []
        out: list[Plant] = []
        for p, *_ in self._versions():
            draw = sample_variants(
                p, self.fresh_variants, self.variant_seed + self.done, self.variant_range,
                (self.limit, -self.limit), steps, self.variant_tries,
            )  # fmt: skip
            self.fresh.setdefault(p.name, []).extend(v.factors for v in draw.kept)
            out.extend(v.plant for v in draw.kept)
        return out

    def _rollouts(
        self, steps: int, plants: Sequence[Plant], lost: Mapping[str, float] | None = None
    ) -> list[RolloutSpec]:
        """Per plant version, in order: references and initial states (steps, families).

        ``lost`` (plant name -> closed-loop score in [0, 1]) adds the focus's step rollouts.
        """
        rng = np.random.default_rng(self.seed + self.done)
        lost = lost or {}
        out: list[RolloutSpec] = []
        for p in plants:
            count = self.rollouts + int(round(self.focus * lost.get(p.name, 0.0) * self.rollouts))
            amps = rng.uniform(-self.limit, self.limit, count) * p.amplitude_scale
            rs, x0s = [np.repeat(amps[:, None], steps, axis=1)], [np.zeros((len(amps), p.order))]
            for i, spec in enumerate(self.families.values()):
                seed = int(spec.get("seed", 0)) + 7919 * (self.done + 1) + 31 * i + self.seed
                own = {**spec, "count": self.family_count, "seed": seed}
                r, x0 = family_references(p, own, steps)
                rs.append(r)
                x0s.append(x0)
            out.append((np.concatenate(rs), np.concatenate(x0s)))
        return out

    def _lost(self, trainer: L.Trainer) -> dict[str, float]:
        """Each plant's latest closed-loop validation score, clipped to [0, 1] (focus only)."""
        if self.focus == 0 and self.focus_beta == 0:
            return {}
        metrics = trainer.callback_metrics
        out = {}
        for name in {p.name for p in self.plants}:
            v = metrics.get(f"val/closed_loop/{name}")
            if v is not None and np.isfinite(float(v)):
                out[name] = float(np.clip(float(v), 0.0, 1.0))
        return out

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
        steps = int(round(self.duration / self.plants[0].dt))
        lost = self._lost(trainer)
        plants = self._round_plants() + self._fresh_plants(steps)
        amps = self._rollouts(steps, plants, lost)
        beta = self.beta * self.beta_decay**self.done
        betas = {k: self.focus_beta * s for k, s in lost.items() if self.focus_beta * s > beta}
        policy = cast(Policy, pl_module.policy)
        was_training = policy.training
        runtime = PolicyRuntime(policy, dm.meta())
        integral = runtime.integral
        takeover = self.takeover
        if takeover == "auto":
            takeover = "tracked" if integral else "bumpless"
        with torch.inference_mode():
            windows, counts = aggregate(
                plants, runtime, beta, amps, self._bounds(dm.train_set), steps,
                dm.history, dm.horizon, takeover, integral, runtime.controls, betas,
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
        record["versions"] = len(plants)
        self.history.append(record)
        log.info("DAgger round %d (beta %.3g): %d windows added", self.done, beta, len(windows))
        if betas:
            log.info("DAgger focus on %s", {k: round(v, 3) for k, v in sorted(betas.items())})
        for key in ("windows", "beta", "versions"):
            pl_module.log(f"dagger/{key}", float(record[key]), logger=False)
