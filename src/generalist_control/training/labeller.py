"""DAgger's expert labeller: LQI plans from the states the learned policy itself visits."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from generalist_control.data.windows import Windows, build_windows
from generalist_control.plants.definition import Plant, pad_states
from generalist_control.simulation.lqi import design_lqi
from generalist_control.simulation.simulate import Trajectory, plant_stepper
from generalist_control.training.sampler import Rollouts
from generalist_control.training.settings import LabellerSettings

__all__ = ["ExpertLabeller", "bumpless_integrator", "expert_plans"]


def expert_plans(
    plant: Plant, x: np.ndarray, z: np.ndarray, r: np.ndarray, horizon: int
) -> np.ndarray:
    """The LQI expert's next ``horizon`` controls (B, N, horizon) from each visited state.

    ``x`` (B, N, n), the integrator ``z`` before each sample's control and ``r`` (B, N; the
    last held beyond the end). ``plans[:, :, 0]`` is the LQI law at the visited state.
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
    """The expert's integrator (B, N) for a bumpless take-over at every sample of a rollout.

    ``z_k`` follows from the ``z_(k-1)`` with which the LQI law gives the applied ``u_(k-1)``:
    the LQI law in velocity form, which never contradicts the demonstrations. ``z_0 = 0``.
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


class ExpertLabeller:
    """Windows of the visited states with the experts' plans as targets (``dagger.labeller``).

    ``history``, ``horizon`` and ``channels`` are the policy's window (``model.channels``).
    """

    def __init__(
        self, settings: LabellerSettings, history: int, horizon: int, channels: Sequence[str]
    ) -> None:
        self.settings, self.history, self.horizon = settings, int(history), int(horizon)
        self.integral = "integral" in channels
        self.controls = "previous_control" in channels

    def bounds(self, train_set: Any, plants: Sequence[Plant]) -> dict[str, np.ndarray]:
        """Per plant name: ``bound_factor`` times its largest state in the training windows."""
        t = train_set.tensors
        out = {}
        for p in plants:
            sel = t["tag"] == p.tag
            peak = t["state"][sel][..., : p.order].abs().amax(dim=(0, 1)).double().numpy()
            out[p.name] = self.settings.bound_factor * np.maximum(peak, 1e-9)
        return out

    def _windows(
        self, p: Plant, tr: Trajectory, z: np.ndarray, bound: np.ndarray
    ) -> tuple[Windows, np.ndarray]:
        """One plant's rollout windows with the expert's plans as targets, and which to keep."""
        steps, horizon = tr.r.shape[1], self.horizon
        B = tr.r.shape[0]
        x = tr.x[:, :steps]
        ok = _in_range(x, bound)  # a diverged run leaves its range first
        x = np.nan_to_num(x)
        if not self.integral:
            z = bumpless_integrator(p, x, tr.u, tr.r)
        plans = expert_plans(p, x, z, tr.r, horizon)
        w = build_windows(
            pad_states(x), tr.r, np.nan_to_num(tr.u),
            np.full(B, p.tag), np.full(B, p.order), self.history, horizon,
            z if self.integral else None, self.controls,
        )  # fmt: skip
        per = steps - horizon + 1
        keep = ok[:, horizon - 1 :].reshape(-1)  # every sample up to the plan's end in range
        target = plans[:, :per].reshape(-1, horizon).astype(np.float32)
        return Windows(w.state, w.mask, w.ref, w.tag, target, w.traj), keep

    def label(
        self, rollouts: Rollouts, bounds: Mapping[str, np.ndarray]
    ) -> tuple[Windows, dict[str, int]]:
        """The labelled windows of a round's ``rollouts``, and how many were kept per plant."""
        parts: list[tuple[Windows, np.ndarray]] = []
        counts: dict[str, int] = {}
        for p, tr, z in zip(rollouts.plants, rollouts.trajectories, rollouts.z, strict=True):
            w, keep = self._windows(p, tr, z, bounds[p.name])
            parts.append((w, keep))
            counts[p.name] = counts.get(p.name, 0) + int(keep.sum())  # variants share a name
        fields = ("state", "mask", "ref", "tag", "target", "traj")
        cat = {k: np.concatenate([getattr(w, k)[keep] for w, keep in parts]) for k in fields}
        return Windows(**cat), counts
