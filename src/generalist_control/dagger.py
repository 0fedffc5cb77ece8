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

:class:`DAggerCallback` runs the rounds during training; :func:`aggregate` is one round.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import lightning as L
import numpy as np
import torch

from generalist_control.lqi import LQIController, design_lqi
from generalist_control.plants import Plant
from generalist_control.runtime import PolicyRuntime, stacked_output
from generalist_control.simulate import Run, plant_stepper, row_slices, simulate_many
from generalist_control.windows import Windows, build_windows, pad_states

__all__ = [
    "DAggerCallback",
    "MixedController",
    "aggregate",
    "bumpless_integrator",
    "expert_plans",
]

log = logging.getLogger(__name__)


class MixedController:
    """Executes ``beta * LQI + (1 - beta) * policy``; records the experts' integrators.

    A :class:`~generalist_control.simulate.BatchController` for
    :func:`~generalist_control.simulate.simulate_many`. After a run, :attr:`z` holds the
    expert integrator *before* each sample's control, shape (rows, N).
    """

    def __init__(self, runtime: PolicyRuntime | None, beta: float) -> None:
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
        self._output = None
        if self.runtime is not None and self.beta < 1.0:
            names = [p.name for p, c in zip(plants, counts, strict=True) for _ in range(c)]
            self.runtime.reset(names)
            if self.runtime.integral:
                self._output = stacked_output(plants, counts)
        self._z: list[np.ndarray] = []

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Mixed control for zero-padded states ``x`` (rows, MAX_ORDER)."""
        u_e, z = np.empty(x.shape[0]), np.empty(x.shape[0])
        for ctrl, n, rows in self._parts:
            z[rows] = ctrl.z
            u_e[rows] = ctrl.step(x[rows, :n], r[rows])
        self._z.append(z)
        if self.runtime is None or self.beta >= 1.0:
            return u_e
        if self._output is None:
            u_p = self.runtime.step(x, r)
        else:
            u_p = self.runtime.step(x, r, self._output(x))
        return self.beta * u_e + (1.0 - self.beta) * u_p

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


def aggregate(
    plants: Sequence[Plant],
    runtime: PolicyRuntime | None,
    beta: float,
    amplitudes: dict[str, np.ndarray],
    bounds: dict[str, np.ndarray],
    steps: int,
    history: int,
    horizon: int,
    takeover: str = "bumpless",
    integral: bool = False,
) -> tuple[Windows, dict[str, int]]:
    """One DAgger round: rollouts of the mixed controller, labelled by the experts.

    Parameters
    ----------
    plants : sequence of Plant
    runtime : PolicyRuntime or None
        The current policy (None with ``beta = 1``: pure expert rollouts).
    beta : float
        Weight of the expert in the executed control.
    amplitudes : dict
        Step amplitudes (plant units) per plant name; one rollout from rest per amplitude.
    bounds : dict
        Per plant, the largest state magnitude (n,) a rollout may reach; windows past the
        first sample outside are dropped.
    steps, history, horizon : int
    takeover : {"bumpless", "tracked"}
        The integrator the expert takes over with: ``"bumpless"`` (default) sets it so
        that the expert's law reproduces the control applied one sample earlier (see
        :func:`bumpless_integrator`); ``"tracked"`` uses the integral of ``r - y`` along
        the rollout, which the policy cannot see in its window unless ``integral``.
    integral : bool
        The windows carry the error integral as their last state channel (a policy trained
        with ``model.integral``); requires ``takeover="tracked"``, since the label must come
        from the integrator the policy sees.

    Returns
    -------
    windows : Windows
        Training windows with the experts' plans as targets.
    counts : dict
        Windows kept per plant.
    """
    if integral and takeover != "tracked":
        raise ValueError(
            "a policy that sees the error integral is labelled from that integrator: "
            "use dagger.takeover=tracked (or auto)"
        )
    runs = [Run(p, np.repeat(amplitudes[p.name][:, None], steps, axis=1)) for p in plants]
    ctrl = MixedController(runtime, beta)
    trajs = simulate_many(runs, ctrl)
    z_all = ctrl.z
    parts, counts, start = [], {}, 0
    for p, run, tr in zip(plants, runs, trajs, strict=True):
        B = run.r.shape[0]
        x, z = tr.x[:, :steps], z_all[start : start + B]
        start += B
        ok = _in_range(x, bounds[p.name])  # a diverged run leaves its range first
        x = np.nan_to_num(x)
        if takeover == "bumpless":
            z = bumpless_integrator(p, x, tr.u, run.r)
        plans = expert_plans(p, x, z, run.r, horizon)
        w = build_windows(
            pad_states(np.nan_to_num(x)), run.r, np.zeros_like(run.r),
            np.full(B, p.tag), np.full(B, p.order), history, horizon,
            z if integral else None,
        )  # fmt: skip
        per = steps - horizon + 1
        keep = ok[:, horizon - 1 :].reshape(-1)  # every sample up to the plan's end in range
        target = plans[:, :per].reshape(-1, horizon).astype(np.float32)
        parts.append((w, target, keep))
        counts[p.name] = int(keep.sum())
    windows = Windows(
        state=np.concatenate([w.state[k] for w, _, k in parts]),
        mask=np.concatenate([w.mask[k] for w, _, k in parts]),
        ref=np.concatenate([w.ref[k] for w, _, k in parts]),
        tag=np.concatenate([w.tag[k] for w, _, k in parts]),
        target=np.concatenate([t[k] for _, t, k in parts]),
        traj=np.concatenate([w.traj[k] for w, _, k in parts]),
    )
    return windows, counts


class DAggerCallback(L.Callback):
    """Aggregate expert-labelled policy rollouts into the training set during training.

    After epoch ``start_epoch`` and then every ``every`` epochs, for ``rounds`` rounds:
    roll the current policy out on every training plant (``rollouts`` steps per plant
    from rest, amplitudes drawn uniformly within the plant's data range), label the
    visited states with :func:`expert_plans`, and append the windows to the data module's
    training set. The trainer must reload its dataloaders every epoch
    (``reload_dataloaders_every_n_epochs=1``; :func:`generalist_control.train.train` sets
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
        dm = trainer.datamodule
        rng = np.random.default_rng(self.seed + self.done)
        amps = {
            p.name: rng.uniform(-self.limit, self.limit, self.rollouts) * p.amplitude_scale
            for p in self.plants
        }
        steps = int(round(self.duration / self.plants[0].dt))
        beta = self.beta * self.beta_decay**self.done
        policy = pl_module.policy
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
        for cb in trainer.callbacks:
            if isinstance(cb, L.pytorch.callbacks.EarlyStopping):
                cb.wait_count = 0
        trainer.should_stop = False
        record = {"round": self.done, "beta": beta, "windows": len(windows), **counts}
        self.history.append(record)
        log.info("DAgger round %d (beta %.3g): %d windows added", self.done, beta, len(windows))
        for key in ("windows", "beta"):
            pl_module.log(f"dagger/{key}", float(record[key]), logger=False)
