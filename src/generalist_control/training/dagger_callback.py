"""The DAgger rounds during training: a Lightning callback around :func:`aggregate`."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any, cast

import lightning as L
import numpy as np
import torch

from generalist_control.common.schema import require_int, require_nonnegative
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.plant import Plant
from generalist_control.plants.variants import DEFAULT_RANGE
from generalist_control.simulation.comparison import closed_loop_score
from generalist_control.simulation.references import family_references
from generalist_control.simulation.simulate import BatchController
from generalist_control.simulation.variants import Variant, sample_variants
from generalist_control.training.actuator import checked_spread
from generalist_control.training.dagger import RolloutSpec, aggregate

__all__ = ["DAggerCallback"]

log = logging.getLogger(__name__)

#: Steps (times each plant's amplitude scale) a fresh-variant pool is screened on: the
#: closed-loop validation's default amplitudes.
SCREEN_AMPLITUDES = (1.0, -3.0)


def _fresh_counts(fresh: Any, pool: Any, worst: Any) -> tuple[int, int, int]:
    """``dagger.fresh_variants``, ``fresh_pool`` and ``fresh_worst`` (None: all), checked.

    Raises
    ------
    ValueError
        A count is not a non-negative integer, the pool is smaller than the fresh variants,
        or more of them are to be the worst than there are.
    """
    m = require_int("dagger.fresh_variants", fresh, minimum=0)
    n = require_int("dagger.fresh_pool", pool, minimum=0)
    if 0 < n < m:
        raise ValueError(
            f"dagger.fresh_pool = {pool} is smaller than dagger.fresh_variants = {fresh}: the "
            "pool the worst are chosen from must hold at least as many; raise it, or set 0 to "
            "take the draw as it comes"
        )
    k = require_int("dagger.fresh_worst", m if worst is None else worst, minimum=0)
    if k > m:
        raise ValueError(
            f"dagger.fresh_worst = {worst} exceeds dagger.fresh_variants = {fresh}: at most "
            "all of the fresh variants can be the worst"
        )
    return m, n, k


def _takeover(takeover: str) -> str:
    """``dagger.takeover``, checked."""
    if takeover not in ("auto", "bumpless", "tracked"):
        raise ValueError(
            f"dagger.takeover must be 'auto', 'bumpless' or 'tracked', got {takeover!r}"
        )
    return takeover


def _control_scales(policy: Policy) -> np.ndarray:
    """The policy's control scale per tag (its normaliser: the RMS of the training controls)."""
    return policy.normaliser.control_scale.detach().cpu().double().numpy()


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
    fresh_pool : int
        0: the fresh variants are the first ``fresh_variants`` of the round's draw. Otherwise
        ``fresh_pool`` (>= ``fresh_variants``) are drawn per plant and the current policy is
        screened on each (:func:`~generalist_control.simulation.comparison.closed_loop_score`
        on steps of :data:`SCREEN_AMPLITUDES` over ``duration``, against each variant's own
        LQI); the ``fresh_variants`` on which its loop is worst are rolled out, so the rounds
        go where the policy fails. Their scores are kept in :attr:`screened`, per plant.
    fresh_worst : int, optional
        With ``fresh_pool``: only this many of the ``fresh_variants`` are the worst of the
        pool's rest; the others are the draw's first, as without a pool, so the rounds keep
        covering the range. None: all are the worst.
    variant_seed, variant_range, variant_tries : int / float / int
    noise : float
        Standard deviation of white noise added to the executed control in every rollout,
        as a fraction of each plant's control scale (the policy's normaliser: the RMS of the
        plant's training controls), so the rollouts leave the smooth closed-loop curve and
        the experts label the corrections of small deviations about it, near the
        equilibrium too (:class:`~generalist_control.training.dagger.MixedController`).
        0: off.
    actuator_lag, actuator_offset : float
        Each rollout row's actuator lags the command by a first-order time constant
        uniform in ``[0, actuator_lag]`` sample periods and adds a constant offset uniform
        in ``+-actuator_offset`` times the plant's control scale
        (:class:`~generalist_control.training.actuator.Actuator`); the windows carry the
        command. 0, 0: off.
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
        fresh_pool: int = 0,
        fresh_worst: int | None = None,
        variant_seed: int = 3001,
        variant_range: float = DEFAULT_RANGE,
        variant_tries: int = 10,
        noise: float = 0.0,
        actuator_lag: float = 0.0,
        actuator_offset: float = 0.0,
    ) -> None:
        self.plants = list(plants)
        if variants is not None:
            variants = require_int("dagger.variants", variants, minimum=0)
        self.variants = variants
        counts = _fresh_counts(fresh_variants, fresh_pool, fresh_worst)
        self.fresh_variants, self.fresh_pool, self.fresh_worst = counts
        self.variant_seed = require_int("dagger.variant_seed", variant_seed, minimum=0)
        self.variant_range = float(variant_range)
        self.variant_tries = require_int("dagger.variant_tries", variant_tries, minimum=1)
        self.fresh: dict[str, list[dict[str, float]]] = {}
        self.screened: dict[str, list[float]] = {}
        self.last_screen: list[float] = []
        self.limit, self.start_epoch, self.every = float(limit), int(start_epoch), int(every)
        self.rounds, self.rollouts, self.duration = int(rounds), int(rollouts), float(duration)
        self.beta, self.beta_decay = float(beta), float(beta_decay)
        self.bound_factor, self.seed = float(bound_factor), int(seed)
        self.takeover = _takeover(takeover)
        self.families = {k: dict(v) for k, v in (families or {}).items()}
        self.family_count = int(family_count)
        self.focus, self.focus_beta = float(focus), float(focus_beta)
        if self.focus < 0 or not 0 <= self.focus_beta <= 1:
            raise ValueError(
                f"dagger.focus must be >= 0 and dagger.focus_beta in [0, 1], "
                f"got {focus!r} and {focus_beta!r}"
            )
        self.noise = require_nonnegative("dagger.noise", noise, "fraction")
        self.actuator_lag, self.actuator_offset = checked_spread(actuator_lag, actuator_offset)
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

    def _fresh_plants(self, steps: int, controller: BatchController | None = None) -> list[Plant]:
        """The round's fresh variants: ``fresh_variants`` per plant, drawn for this round.

        With ``fresh_pool``, the worst of each plant's pool under ``controller`` (the
        current policy's loop; required then, see :meth:`_worst`).
        """
        if not self.fresh_variants:
            return []
        wanted = max(self.fresh_variants, self.fresh_pool)
        pools = [
            sample_variants(
                p, wanted, self.variant_seed + self.done, self.variant_range,
                (self.limit, -self.limit), steps, self.variant_tries,
            ).kept
            for p, *_ in self._versions()
        ]  # fmt: skip
        if wanted > self.fresh_variants:
            if controller is None:
                raise ValueError("dagger.fresh_pool: screening the pool needs the policy's loop")
            pools = self._worst(pools, controller, steps)
        out: list[Plant] = []
        for pool in pools:
            for v in pool:
                self.fresh.setdefault(v.plant.name, []).append(v.factors)
                out.append(v.plant)
        return out

    def _worst(
        self, pools: list[list[Variant]], controller: BatchController, steps: int
    ) -> list[list[Variant]]:
        """Of each pool, the draw's first and the ``fresh_worst`` worst of the rest, in order.

        The draw's first ``fresh_variants - fresh_worst`` are kept as drawn; the rest of the
        pool is screened in one batched :func:`closed_loop_score` of ``controller`` (steps of
        :data:`SCREEN_AMPLITUDES`, ``steps`` samples, each against its own LQI), and the
        ``fresh_worst`` with the highest scores join them (ties keep the draw's order). The
        chosen scores go to :attr:`screened`.
        """
        first = self.fresh_variants - self.fresh_worst
        flat = [v for pool in pools for v in pool[first:]]
        if not self.fresh_worst or not flat:
            return [pool[:first] for pool in pools]
        labels = [f"{v.plant.name}/{k}" for k, v in enumerate(flat)]
        scores = closed_loop_score(
            controller, [v.plant for v in flat], SCREEN_AMPLITUDES,
            steps * flat[0].plant.dt, labels,
        )  # fmt: skip
        out, start, self.last_screen = [], 0, []
        for pool in pools:
            own = [scores[labels[start + j]] for j in range(len(pool) - first)]
            start += len(own)
            chosen = sorted(np.argsort(-np.asarray(own), kind="stable")[: self.fresh_worst])
            out.append(pool[:first] + [pool[first + j] for j in chosen])
            if pool:
                self.screened.setdefault(pool[0].plant.name, []).extend(own[j] for j in chosen)
                self.last_screen.extend(own[j] for j in chosen)
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

    def _noise(self, policy: Policy, plants: Sequence[Plant]) -> dict[str, float] | None:
        """Per plant name: ``noise`` times the policy's control scale for its tag (None: off)."""
        if not self.noise:
            return None
        scale = _control_scales(policy)
        return {p.name: self.noise * float(scale[p.tag]) for p in plants}

    def _actuator(
        self, policy: Policy, plants: Sequence[Plant]
    ) -> dict[str, tuple[float, float]] | None:
        """Per plant name: the lag, and the offset in its control units (None: off)."""
        if not (self.actuator_lag or self.actuator_offset):
            return None
        scale, off = _control_scales(policy), self.actuator_offset
        return {p.name: (self.actuator_lag, off * float(scale[p.tag])) for p in plants}

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
            # a pool is screened with the round's runtime; aggregate resets it afterwards
            plants = self._round_plants() + self._fresh_plants(steps, RuntimeAdapter(runtime))
            amps = self._rollouts(steps, plants, lost)
            windows, counts = aggregate(
                plants, runtime, beta, amps, self._bounds(dm.train_set), steps,
                dm.history, dm.horizon, takeover, integral, runtime.controls, betas,
                self._noise(policy, plants), self.seed + 7901 * (self.done + 1),
                self._actuator(policy, plants),
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
        if self.fresh_pool > self.fresh_variants:  # the chosen variants' median screening score
            record["screened"] = float(np.median(self.last_screen))
        self.history.append(record)
        log.info("DAgger round %d (beta %.3g): %d windows added", self.done, beta, len(windows))
        if betas:
            log.info("DAgger focus on %s", {k: round(v, 3) for k, v in sorted(betas.items())})
        for key in ("windows", "beta", "versions", "screened"):
            if key in record:
                pl_module.log(f"dagger/{key}", float(record[key]), logger=False)
