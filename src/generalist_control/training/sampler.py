"""DAgger's rollout sampler: which rollouts a round runs, and the loop that runs them.

Steps from rest and the data's reference families, per plant version, executed as
``beta * LQI + (1 - beta) * policy``, optionally with control noise and a random actuator.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.plants.definition import Plant
from generalist_control.simulation.comparison import ClosedLoopScore
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.references import family_references, family_spec
from generalist_control.simulation.simulate import Run, Trajectory, row_slices, simulate_many
from generalist_control.simulation.variant_sampling import sample_variants
from generalist_control.training.settings import RolloutData, SamplerSettings

__all__ = [
    "Actuator",
    "InTurn",
    "MixedController",
    "RolloutSampler",
    "Rollouts",
    "WorstFirst",
    "lag_mix",
    "run_rollouts",
]


def lag_mix(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A first-order lag's mean weight and decay over one sample (time constants ``tau``).

    For a command ``u`` held from the lag's output ``s``, the mean output is
    ``u + mix (s - u)`` and the end value ``u + decay (s - u)``; 0 at ``tau = 0``.

    Examples
    --------
    >>> mix, decay = lag_mix(np.array([0.0, 0.6]))
    >>> np.round(mix, 3).tolist(), np.round(decay, 3).tolist()
    ([0.0, 0.487], [0.0, 0.189])
    """
    tau = np.asarray(tau, dtype=float)
    safe = np.where(tau > 0, tau, 1.0)
    decay = np.where(tau > 0, np.exp(-1.0 / safe), 0.0)
    return tau * (1.0 - decay), decay


class Actuator:
    """A random actuator per row: a lag (uniform in ``[0, lag]`` samples) and an offset.

    The offset is uniform in ``+-offset``, both drawn from ``rng``; the windows keep the
    command, so the identifier learns to name a plant whose actuator lags or is offset.
    """

    def __init__(self, lag: np.ndarray, offset: np.ndarray, rng: np.random.Generator) -> None:
        lag, offset = np.asarray(lag, dtype=float), np.asarray(offset, dtype=float)
        if lag.shape != offset.shape or lag.ndim != 1:
            raise ValueError(f"lag {lag.shape} and offset {offset.shape} must be (rows,) alike")
        for name, v in (("lag", lag), ("offset", offset)):
            if not np.all(np.isfinite(v) & (v >= 0)):
                raise ValueError(f"the actuator's {name} must be finite and >= 0, got {v}")
        self.tau = lag * rng.random(lag.shape[0])
        self.d = offset * rng.uniform(-1.0, 1.0, offset.shape[0])
        self.mix, self.decay = lag_mix(self.tau)
        self.s = np.zeros(lag.shape[0])

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """What the plants receive over this sample for commands ``u`` (rows,)."""
        u = np.asarray(u, dtype=float)
        applied = u + self.mix * (self.s - u) + self.d
        self.s = u + self.decay * (self.s - u)
        return applied


def _per_row(
    plants: Sequence[Plant], counts: Sequence[int], values: Mapping[str, float]
) -> np.ndarray:
    """Each row's value: its plant's entry in ``values`` (by name), else 0."""
    per = zip(plants, counts, strict=True)
    return np.concatenate([np.full(c, float(values.get(p.name, 0.0))) for p, c in per])


class MixedController:
    """Executes ``beta * LQI + (1 - beta) * policy``.

    Each step appends the experts' integrators to :attr:`integrators` and, with an actuator,
    the command to :attr:`commands` (both (rows,) per sample).

    ``noise`` (plant name -> std, control units) adds white noise to the executed control (as
    DART does); ``actuator`` (plant name -> (lag, offset)) puts an :class:`Actuator` between
    command and plant; both draw from ``seed``.
    """

    def __init__(
        self,
        runtime: PolicyRuntime | None,
        beta: float,
        noise: Mapping[str, float] | None = None,
        seed: int = 0,
        actuator: Mapping[str, tuple[float, float]] | None = None,
    ) -> None:
        self.actuator = dict(actuator or {})
        self.noise = {k: float(v) for k, v in (noise or {}).items()}
        if any(not np.isfinite(v) or v < 0 for v in self.noise.values()):
            raise ValueError(f"control noise must be finite and >= 0, got {self.noise}")
        self.seed = int(seed)
        if runtime is None and beta != 1.0:
            raise ValueError("without a policy runtime, beta must be 1 (pure expert)")
        self.runtime, self.beta = runtime, float(beta)

    def reset(self, plants: Sequence[Plant], counts: Sequence[int]) -> None:
        """One LQI expert per plant group; the policy over all rows."""
        self._parts = []
        for plant, count, rows in zip(plants, counts, row_slices(counts), strict=True):
            ctrl = LQIController(plant)
            ctrl.reset(count)
            self._parts.append((ctrl, plant.order, rows))
        self._sigma = _per_row(plants, counts, self.noise)
        self._rng = np.random.default_rng(self.seed)
        self._act = None
        if self.actuator:
            lag = _per_row(plants, counts, {k: v[0] for k, v in self.actuator.items()})
            off = _per_row(plants, counts, {k: v[1] for k, v in self.actuator.items()})
            self._act = Actuator(lag, off, self._rng)
        self._policy = None
        if self.runtime is not None and self.beta < 1.0:
            self._policy = RuntimeAdapter(self.runtime)
            self._policy.reset(plants, counts)
        self.integrators: list[np.ndarray] = []
        self.commands: list[np.ndarray] = []

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Mixed control for zero-padded states ``x`` (rows, MAX_ORDER)."""
        u_e, z = np.empty(x.shape[0]), np.empty(x.shape[0])
        for ctrl, n, rows in self._parts:
            z[rows] = ctrl.z
            u_e[rows] = ctrl.step(x[rows, :n], r[rows])
        self.integrators.append(z)
        u = u_e
        if self._policy is not None:
            u_p = self._policy.step(x, r)  # NaN: a run the runtime refused (outside its range)
            u_p = np.where(np.isnan(u_p), u_e, u_p)  # the expert takes that run over
            u = self.beta * u_e + (1.0 - self.beta) * u_p
        if self._sigma.any():
            u = u + self._sigma * self._rng.standard_normal(u.shape[0])
        if self._policy is not None:
            self._policy.record_applied(u)  # the policy's previous-control channel: what ran
        if self._act is None:
            return u
        self.commands.append(u)  # the (noisy) mixed command, before the actuator
        return self._act(u)


class InTurn:
    """``train_families.dagger_pick``: a family's plants join DAgger ``k`` at a time, in turn."""

    def __call__(
        self, plants: Sequence[Plant], k: int, round_index: int, runtime: PolicyRuntime | None
    ) -> list[Plant]:
        """Round ``round_index``'s ``k`` of ``plants`` (at most all)."""
        k = min(k, len(plants))
        return [plants[(round_index * k + j) % len(plants)] for j in range(k)]


class WorstFirst:
    """``train_families.dagger_pick``: of ``pool`` plants in turn, the ``k`` it controls worst.

    Each round scores the pool by the closed-loop validation's measure (steps from rest
    against LQI, :class:`ClosedLoopScore`) under the policy as it is, and rolls out the worst:
    the plants it loses get the expert's labels where its own loop takes them
    (docs/notes/family-policy.md, experiment 14).
    """

    def __init__(self, pool: int) -> None:
        if pool < 1:
            raise ValueError(f"train_families.dagger_pick.pool must be >= 1, got {pool}")
        self.pool = int(pool)

    def __call__(
        self, plants: Sequence[Plant], k: int, round_index: int, runtime: PolicyRuntime | None
    ) -> list[Plant]:
        """The ``k`` worst-controlled of round ``round_index``'s pool, worst first.

        Raises
        ------
        ValueError
            Without a ``runtime`` to score.
        """
        if not plants or k < 1:
            return []
        if runtime is None:
            raise ValueError("WorstFirst scores the policy: give the round's runtime")
        pool = InTurn()(plants, max(self.pool, k), round_index, None)
        scores = ClosedLoopScore(pool)(RuntimeAdapter(runtime))
        return sorted(pool, key=lambda p: -scores[p.name])[: min(k, len(pool))]


#: One plant's rollouts: references (B, steps) and initial states (B, n) or None (rest).
RolloutSpec = tuple[np.ndarray, np.ndarray | None]


@dataclass(frozen=True)
class Rollouts:
    """A round's rollouts: per plant version its trajectories and the experts' integrators."""

    plants: list[Plant]
    trajectories: list[Trajectory]
    z: list[np.ndarray]


def run_rollouts(
    plants: Sequence[Plant],
    specs: Sequence[RolloutSpec],
    runtime: PolicyRuntime | None,
    beta: float,
    noise: Mapping[str, float] | None = None,
    seed: int = 0,
    actuator: Mapping[str, tuple[float, float]] | None = None,
) -> Rollouts:
    """Run every plant's rollouts (``specs``) under the :class:`MixedController`."""
    runs = [Run(p, r, x0) for p, (r, x0) in zip(plants, specs, strict=True)]
    ctrl = MixedController(runtime, beta, noise, seed, actuator)
    trajs, slices = simulate_many(runs, ctrl), row_slices([len(r.r) for r in runs])
    if actuator:  # the windows carry what was commanded, as a deployed policy's do
        cmd = np.stack(ctrl.commands, axis=1)
        trajs = [replace(tr, u=cmd[sl]) for tr, sl in zip(trajs, slices, strict=True)]
    z = np.stack(ctrl.integrators, axis=1)  # the expert's integrator before each sample's control
    return Rollouts(list(plants), trajs, [z[sl] for sl in slices])


class RolloutSampler:
    """The rollouts of each DAgger round (``dagger.sampler``) of ``plants`` and their variants.

    ``data``: the data recipe's rollout facts; ``seed`` seeds round ``i``'s draws (``seed + i``);
    ``rotating`` plants (a family's) join ``per_round`` at a time, chosen by ``pick``
    (:class:`InTurn` by default).
    """

    def __init__(
        self,
        plants: Sequence[Plant],
        settings: SamplerSettings,
        data: RolloutData,
        seed: int,
        rotating: Sequence[Plant] = (),
        per_round: int = 0,
        pick: InTurn | WorstFirst | None = None,
    ) -> None:
        self.plants, self.settings, self.data = list(plants), settings, data
        self.rotating, self.per_round = list(rotating), int(per_round)
        self.pick = pick or InTurn()
        self.limit, self.seed = data.amplitude_limit, int(seed)
        self.families = data.families if settings.families else {}
        #: per plant name, the factors of every fresh variant rolled out so far
        self.fresh: dict[str, list[dict[str, float]]] = {}

    def steps(self) -> int:
        """Samples per rollout."""
        return int(round(self.settings.duration / self.plants[0].dt))

    def round_plants(self, round_index: int, runtime: PolicyRuntime | None = None) -> list[Plant]:
        """The round's plant versions: the data's (all, or in turn), fresh variants, rotating.

        ``runtime``: the policy as it is, for a pick that scores it.
        """
        groups: dict[str, list[Plant]] = {}  # by name, each its nominal version first
        for p in self.plants:
            groups.setdefault(p.name, []).append(p)
        variants, out = self.settings.variants, list(self.plants)
        if variants is not None and variants.data is not None:
            out = []
            for nominal, *rest in groups.values():
                out += [nominal, *InTurn()(rest, variants.data, round_index, None)]
        if variants is not None and variants.fresh:
            for nominal, *_ in groups.values():
                draw = sample_variants(
                    nominal, variants.fresh, variants.seed + round_index, self.data.variant_range,
                    (self.limit, -self.limit), self.steps(), self.data.variant_tries,
                )  # fmt: skip
                for v in draw.kept:
                    self.fresh.setdefault(v.plant.name, []).append(v.factors)
                    out.append(v.plant)
        return out + self.pick(self.rotating, self.per_round, round_index, runtime)

    def specs(self, round_index: int, plants: Sequence[Plant]) -> list[RolloutSpec]:
        """Per plant version, in order: the round's references and initial states."""
        steps, n = self.steps(), self.settings.families
        rng = np.random.default_rng(self.seed + round_index)
        out: list[RolloutSpec] = []
        for p in plants:
            amps = rng.uniform(-self.limit, self.limit, self.settings.rollouts)
            amps = amps * p.amplitude_scale
            rs, x0s = [np.repeat(amps[:, None], steps, axis=1)], [np.zeros((len(amps), p.order))]
            for i, spec in enumerate(self.families.values()):
                seed = family_spec(spec)["seed"] + 7919 * (round_index + 1) + 31 * i + self.seed
                r, x0 = family_references(p, {**spec, "count": n, "seed": seed}, steps)
                rs.append(r)
                x0s.append(x0)
            out.append((np.concatenate(rs), np.concatenate(x0s)))
        return out

    def run(self, round_index: int, runtime: PolicyRuntime, beta: float) -> Rollouts:
        """Round ``round_index``'s rollouts of ``runtime``'s policy, the expert's share beta."""
        plants = self.round_plants(round_index, runtime)
        specs = self.specs(round_index, plants)
        scale = runtime.policy.normaliser.control_scale.detach().cpu().double().numpy()
        noise = None
        if self.settings.noise:
            noise = {p.name: self.settings.noise * float(scale[p.tag]) for p in plants}
        act = self.settings.actuator
        actuator = None
        if act is not None and (act.lag or act.offset):
            actuator = {p.name: (act.lag, act.offset * float(scale[p.tag])) for p in plants}
        seed = self.seed + 7901 * (round_index + 1)
        return run_rollouts(plants, specs, runtime, beta, noise, seed, actuator)
