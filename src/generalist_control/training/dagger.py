"""DAgger: LQI labels on the states the learned policy itself visits in closed loop.

The demonstrations are step responses from rest: for each plant they trace essentially
one curve per amplitude, so a policy that imitates them well can still have the wrong
*feedback* off that curve, and a small error in the feedback gain of an open-loop unstable
plant (magnetic levitation, the cart-pole, ball and beam) diverges. DAgger (Ross et al.,
2011) fixes the distribution: roll the current policy out, ask the expert what it would
have done at every visited state, and add those windows to the training set.

The LQI expert has an integrator ``z`` that the policy's window does not show. The label
at sample ``k`` is the control sequence the expert would apply if it took over at ``k``
with a *bumpless* integrator, set so that its law reproduces the control applied at
``k - 1`` (:func:`bumpless_integrator`): ``u_k = -Kx x_k - Ki z_k``, then the plant and the
integrator advance under the expert's own controls for the next ``K - 1`` samples
(:func:`expert_plans`). That label is a function of the window, equals the demonstrations'
label on the expert's own trajectories, and integrates a persistent error. (Integrating
``r - y`` along the rollout instead, ``takeover="tracked"``, gives labels that depend on
the whole past; in our runs they made the policy worse round after round.) A policy
trained with ``model.integral`` sees that integral itself, so there the label is simply the
expert's plan from the augmented state ``[x; z]`` the policy is in (``takeover="tracked"``,
chosen by the default ``"auto"``). Rollouts
execute ``beta * u_expert + (1 - beta) * u_policy`` (``beta`` decays over the rounds); runs
that leave the plant's data range are cut where they leave it.

:class:`~generalist_control.training.dagger_callback.DAggerCallback` runs the rounds during
training; :func:`aggregate` is one round.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from generalist_control.data.windows import Windows, build_windows
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.plants.plant import Plant, pad_states
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.simulate import (
    Run,
    Trajectory,
    plant_stepper,
    row_slices,
    simulate_many,
)
from generalist_control.training.actuator import Actuator

__all__ = [
    "MixedController",
    "aggregate",
    "bumpless_integrator",
    "expert_plans",
]


def _per_row(
    plants: Sequence[Plant], counts: Sequence[int], values: Mapping[str, float], default: float
) -> np.ndarray:
    """Each row's value: its plant's entry in ``values`` (by name), else ``default``."""
    per = zip(plants, counts, strict=True)
    return np.concatenate([np.full(c, float(values.get(p.name, default))) for p, c in per])


class MixedController:
    """Executes ``beta * LQI + (1 - beta) * policy``; records the experts' integrators.

    ``betas`` overrides ``beta`` for the plants it names (variants share their plant's name).
    ``noise`` (plant name -> standard deviation, in the plant's control units) adds zero-mean
    white noise to the executed control of that plant's rows, drawn from a generator seeded
    with ``seed`` at every :meth:`reset`: the rollouts then visit states off the smooth
    closed-loop curve, where the experts label how they would correct a small deviation
    (noise injection, as in DART: Laskey et al., 2017). The policy's runtime is told the
    executed control
    (:meth:`~generalist_control.deploy.runtime.PolicyRuntime.record_applied`), so a policy
    that reads its previous control (``model.control_history``) sees the control that moved
    the plant, as in the windows it is trained on.

    ``actuator`` (plant name -> (lag, offset), :class:`~generalist_control.training.actuator.
    Actuator`) puts a random first-order lag and constant offset of each row's own between
    the (noisy) mixed command and that plant's rows, drawn from the same generator at
    :meth:`reset`. The runtime is then told the command, which is all a deployed policy
    knows, and :attr:`commanded` holds it for the windows.

    A :class:`~generalist_control.simulation.simulate.BatchController` for
    :func:`~generalist_control.simulation.simulate.simulate_many`. After a run, :attr:`z` holds the
    expert integrator *before* each sample's control, shape (rows, N).
    """

    def __init__(
        self,
        runtime: PolicyRuntime | None,
        beta: float,
        betas: Mapping[str, float] | None = None,
        noise: Mapping[str, float] | None = None,
        seed: int = 0,
        actuator: Mapping[str, tuple[float, float]] | None = None,
    ) -> None:
        self.actuator = dict(actuator or {})
        self.betas = {k: float(v) for k, v in (betas or {}).items()}
        self.noise = {k: float(v) for k, v in (noise or {}).items()}
        if any(not np.isfinite(v) or v < 0 for v in self.noise.values()):
            raise ValueError(f"control noise must be finite and >= 0, got {self.noise}")
        self.seed = int(seed)
        if runtime is None and any(b != 1.0 for b in (beta, *self.betas.values())):
            raise ValueError("without a policy runtime, beta must be 1 (pure expert)")
        self.runtime, self.beta = runtime, float(beta)

    def reset(self, plants: Sequence[Plant], counts: Sequence[int]) -> None:
        """One LQI expert per plant group; the policy over all rows."""
        self._parts = []
        for plant, count, rows in zip(plants, counts, row_slices(counts), strict=True):
            ctrl = LQIController(plant)
            ctrl.reset(count)
            self._parts.append((ctrl, plant.order, rows))
        self._beta = _per_row(plants, counts, self.betas, self.beta)
        self._sigma = _per_row(plants, counts, self.noise, 0.0)
        self._rng = np.random.default_rng(self.seed)
        self._act = None
        if self.actuator:
            lag = _per_row(plants, counts, {k: v[0] for k, v in self.actuator.items()}, 0.0)
            off = _per_row(plants, counts, {k: v[1] for k, v in self.actuator.items()}, 0.0)
            self._act = Actuator(lag, off, self._rng)
        self._policy = None
        if self.runtime is not None and bool(np.any(self._beta < 1.0)):
            self._policy = RuntimeAdapter(self.runtime)
            self._policy.reset(plants, counts)
        self._z: list[np.ndarray] = []
        self._cmd: list[np.ndarray] = []

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Mixed control for zero-padded states ``x`` (rows, MAX_ORDER)."""
        u_e, z = np.empty(x.shape[0]), np.empty(x.shape[0])
        for ctrl, n, rows in self._parts:
            z[rows] = ctrl.z
            u_e[rows] = ctrl.step(x[rows, :n], r[rows])
        self._z.append(z)
        if self._policy is None:
            return self._actuate(self._noisy(u_e))
        u_p = self._policy.step(x, r)  # NaN: a run the runtime refused (outside its range)
        u_p = np.where(np.isnan(u_p), u_e, u_p)  # the expert takes that run over
        u = self._noisy(self._beta * u_e + (1.0 - self._beta) * u_p)
        self._policy.record_applied(u)  # the policy's previous-control channel: what ran
        return self._actuate(u)

    def _actuate(self, u: np.ndarray) -> np.ndarray:
        """What the plants receive for the command ``u`` (``u`` itself without an actuator)."""
        if self._act is None:
            return u
        self._cmd.append(u)
        return self._act(u)

    @property
    def commanded(self) -> np.ndarray:
        """The (noisy) mixed command of each sample, (rows, N), before the actuator (with one)."""
        return np.stack(self._cmd, axis=1)

    def _noisy(self, u: np.ndarray) -> np.ndarray:
        """``u`` plus the rows' control noise (unchanged where there is none)."""
        if not self._sigma.any():
            return u
        return u + self._sigma * self._rng.standard_normal(u.shape[0])

    @property
    def z(self) -> np.ndarray:
        """Expert integrator before each sample's control, (rows, N)."""
        return np.stack(self._z, axis=1)


def expert_plans(
    plant: Plant, x: np.ndarray, z: np.ndarray, r: np.ndarray, horizon: int
) -> np.ndarray:
    """The LQI expert's next ``horizon`` controls from each state of each trajectory.

    Parameters
    ----------
    plant : Plant
    x : ndarray, shape (B, N, n)
        Visited states (deviations).
    z : ndarray, shape (B, N)
        Expert integrator at each visited state (before that sample's control).
    r : ndarray, shape (B, N)
        References; beyond the last sample the last one is held.
    horizon : int

    Returns
    -------
    ndarray, shape (B, N, horizon)
        ``plans[b, k, j]``: the expert's control at sample ``k + j`` had it taken over at
        ``k``. ``plans[:, :, 0]`` is the LQI law at the visited state.
    """
    gains = design_lqi(plant)
    advance = plant_stepper(plant)
    B, N, n = x.shape
    xs, zs = x.reshape(-1, n).copy(), z.reshape(-1).copy()
    idx = np.arange(N)
    plans = np.empty((B * N, horizon))
    for j in range(horizon):
        rj = r[:, np.minimum(idx + j, N - 1)].reshape(-1)
        u = -(xs @ gains.Kx) - gains.Ki * zs
        plans[:, j] = u
        if j + 1 < horizon:
            zs = zs + plant.dt * (rj - plant.output(xs))
            xs = advance(xs, u)
    return plans.reshape(B, N, horizon)


def bumpless_integrator(plant: Plant, x: np.ndarray, u: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The expert's integrator for a bumpless take-over at every sample of a rollout.

    At sample ``k`` the integrator is set so that the LQI law reproduces the control that
    was actually applied at ``k - 1``, ``z_(k-1) = -(u_(k-1) + Kx x_(k-1)) / Ki``, and then
    integrates that sample's error: ``z_k = z_(k-1) + dt (r_(k-1) - y_(k-1))``. The label
    ``u_k = u_(k-1) - Kx (x_k - x_(k-1)) - Ki dt (r_(k-1) - y_(k-1))`` is the LQI law in
    velocity form: a function of the last two samples of the window (for a linear plant
    ``u_(k-1)`` follows from ``x_k - Ad x_(k-1)``), so it never contradicts the
    demonstrations (on them it *is* the expert's label) and, at a biased equilibrium, it
    integrates the error, teaching the policy integral action. At ``k = 0`` (from rest) the
    integrator is zero, as in the demonstrations.

    Parameters
    ----------
    plant : Plant
    x : ndarray, shape (B, N, n)
    u : ndarray, shape (B, N)
        Controls applied.
    r : ndarray, shape (B, N)

    Returns
    -------
    ndarray, shape (B, N)
    """
    g = design_lqi(plant)
    z = np.zeros(u.shape)
    prev = -(u[:, :-1] + x[:, :-1] @ g.Kx) / g.Ki
    z[:, 1:] = prev + plant.dt * (
        r[:, :-1] - plant.output(x[:, :-1].reshape(-1, plant.order)).reshape(r[:, :-1].shape)
    )
    return z


def _in_range(x: np.ndarray, bound: np.ndarray) -> np.ndarray:
    """(B, N) bool: sample inside the plant's range, and every sample before it too."""
    ok = np.all(np.abs(x) <= bound, axis=2) & np.all(np.isfinite(x), axis=2)
    return np.cumprod(ok, axis=1).astype(bool)


#: One plant's rollouts: step amplitudes, or references (B, steps) and initial states.
RolloutSpec = np.ndarray | tuple[np.ndarray, np.ndarray | None]


def _references(spec: RolloutSpec, steps: int) -> tuple[np.ndarray, np.ndarray | None]:
    """References (B, steps) and initial states of one plant's rollouts."""
    if isinstance(spec, tuple):
        return spec
    return np.repeat(np.asarray(spec, dtype=float)[:, None], steps, axis=1), None


def _specs(
    plants: Sequence[Plant], amplitudes: Mapping[str, RolloutSpec] | Sequence[RolloutSpec]
) -> list[RolloutSpec]:
    """Each plant's rollout spec: by name from a mapping, or in order from a sequence."""
    if isinstance(amplitudes, Mapping):
        return [amplitudes[p.name] for p in plants]
    if len(amplitudes) != len(plants):
        raise ValueError(f"{len(amplitudes)} rollout specs for {len(plants)} plants")
    return list(amplitudes)


def _labelled_windows(
    p: Plant,
    tr: Trajectory,
    z: np.ndarray,
    bound: np.ndarray,
    history: int,
    horizon: int,
    takeover: str,
    integral: bool,
    controls: bool = False,
) -> tuple[Windows, np.ndarray]:
    """One plant's rollout windows with the expert's plans as targets, and which to keep."""
    steps = tr.r.shape[1]
    B = tr.r.shape[0]
    x = tr.x[:, :steps]
    ok = _in_range(x, bound)  # a diverged run leaves its range first
    x = np.nan_to_num(x)
    if takeover == "bumpless":
        z = bumpless_integrator(p, x, tr.u, tr.r)
    plans = expert_plans(p, x, z, tr.r, horizon)
    w = build_windows(
        pad_states(np.nan_to_num(x)), tr.r, np.nan_to_num(tr.u),
        np.full(B, p.tag), np.full(B, p.order), history, horizon,
        z if integral else None, controls,
    )  # fmt: skip
    per = steps - horizon + 1
    keep = ok[:, horizon - 1 :].reshape(-1)  # every sample up to the plan's end in range
    target = plans[:, :per].reshape(-1, horizon).astype(np.float32)
    return Windows(w.state, w.mask, w.ref, w.tag, target, w.traj), keep


def _check_takeover(takeover: str, integral: bool) -> None:
    """A policy that sees the error integral is labelled from that integrator."""
    if integral and takeover != "tracked":
        raise ValueError(
            "a policy that sees the error integral is labelled from that integrator: "
            "use dagger.takeover=tracked (or auto)"
        )


def _commanded(
    trajs: Sequence[Trajectory], commanded: np.ndarray, rows: Sequence[slice]
) -> list[Trajectory]:
    """The rollouts with the commands (rows, N) in place of what reached their plants."""
    return [replace(tr, u=commanded[sl]) for tr, sl in zip(trajs, rows, strict=True)]


def aggregate(
    plants: Sequence[Plant],
    runtime: PolicyRuntime | None,
    beta: float,
    amplitudes: Mapping[str, RolloutSpec] | Sequence[RolloutSpec],
    bounds: Mapping[str, np.ndarray],
    steps: int,
    history: int,
    horizon: int,
    takeover: str = "bumpless",
    integral: bool = False,
    controls: bool = False,
    betas: Mapping[str, float] | None = None,
    noise: Mapping[str, float] | None = None,
    noise_seed: int = 0,
    actuator: Mapping[str, tuple[float, float]] | None = None,
) -> tuple[Windows, dict[str, int]]:
    """One DAgger round: rollouts of the mixed controller, labelled by the experts.

    ``runtime`` is the current policy (None with ``beta = 1``: pure expert rollouts) and
    ``beta`` the expert's weight in the executed control. ``amplitudes`` gives, per plant
    name (or per entry of ``plants``, in order, as plant variants share a name), the step
    amplitudes (one rollout from rest each), or the rollouts' references (B, steps) and
    initial states (B, n) (the data's families), and ``bounds`` the largest state
    magnitude (n,) a rollout may reach (windows past the first sample outside are dropped).
    ``takeover`` is the expert's integrator: ``"bumpless"`` (:func:`bumpless_integrator`)
    or ``"tracked"``, the integral of ``r - y`` along the rollout. With ``integral`` the
    windows carry that integral as a state channel (``model.integral``), which requires
    ``"tracked"``. With ``controls`` they carry the control executed one sample earlier
    (``model.control_history``), and so does the policy's runtime during the rollout
    (:class:`MixedController` tells it the executed mix). ``betas``, ``noise``, ``actuator``:
    per plant name, an expert share, noise on the executed control, a random actuator lag
    and offset (windows carry the command; :class:`MixedController`), labels unchanged.

    Returns
    -------
    windows : Windows
        Training windows with the experts' plans as targets.
    counts : dict
        Windows kept per plant.
    """
    _check_takeover(takeover, integral)
    specs = _specs(plants, amplitudes)
    runs = [Run(p, *_references(spec, steps)) for p, spec in zip(plants, specs, strict=True)]
    ctrl = MixedController(runtime, beta, betas, noise, noise_seed, actuator)
    trajs, slices = simulate_many(runs, ctrl), row_slices([len(r.r) for r in runs])
    if actuator:  # the windows carry what was commanded, as a deployed policy's do
        trajs = _commanded(trajs, ctrl.commanded, slices)
    z_all = ctrl.z
    parts: list[tuple[Windows, np.ndarray]] = []
    counts: dict[str, int] = {}
    for p, tr, rows in zip(plants, trajs, slices, strict=True):
        w, keep = _labelled_windows(
            p, tr, z_all[rows], bounds[p.name], history, horizon, takeover, integral, controls
        )
        parts.append((w, keep))
        counts[p.name] = counts.get(p.name, 0) + int(keep.sum())  # variants share a name
    fields = ("state", "mask", "ref", "tag", "target", "traj")
    cat = {k: np.concatenate([getattr(w, k)[keep] for w, keep in parts]) for k in fields}
    return Windows(**cat), counts
