"""Does the policy settle at its set point? Its closed loop linearised there.

A learned policy's loop need not be stable in the small where it should rest; if it is not,
it cannot settle (docs/evaluation.md, "The set-point check", says how this is measured).
"""

from __future__ import annotations

import copy
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager

import numpy as np
import pandas as pd
import torch
from scipy.optimize import brentq

from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.rest_loop import closed_loop_matrix, equilibrium, rest_window
from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.lqi import design_lqi, sampled_closed_loop
from generalist_control.simulation.simulate import (
    Run,
    Trajectory,
    discretise,
)

__all__ = [
    "closed_loop_matrix",
    "equilibrium",
    "hold_runs",
    "rest_radii",
    "setpoint_summary",
    "tail_table",
]


@contextmanager
def _one_thread() -> Iterator[None]:
    """Torch on one thread for the check's small float64 forwards (more only wait)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _control(policy: torch.nn.Module, window: Sequence[torch.Tensor]) -> torch.Tensor:
    """The policy's first control for ``window`` (a scalar tensor)."""
    u, _ = policy(*window)
    return u[0, 0]


def _integral_at(
    policy: torch.nn.Module,
    window: Sequence[torch.Tensor],
    u_star: float,
    z0: float,
    points: int = 401,
) -> tuple[float, float]:
    """``(z*, residual)`` nearest ``z0`` on a grid refined by Brent's method (none: NaN)."""
    width = max(1.0, abs(z0))
    grid = z0 + np.linspace(-width, width, points)
    state, mask, ref, tag = window
    batch = state.detach().repeat(points, 1, 1)
    batch[..., MAX_ORDER] = torch.as_tensor(grid)[:, None]
    with torch.no_grad():
        u, _ = policy(batch, mask.repeat(points, 1, 1), ref.repeat(points, 1), tag.repeat(points))
    resid = u[:, 0].numpy() - u_star
    flips = np.flatnonzero(np.sign(resid[:-1]) * np.sign(resid[1:]) <= 0)
    if flips.size == 0:
        return float("nan"), float(np.abs(resid).min())
    i = int(flips[np.argmin(np.abs(grid[flips] - z0))])

    def f(z: float) -> float:
        s = state.detach().clone()
        s[..., MAX_ORDER] = z
        with torch.no_grad():
            return float(_control(policy, (s, mask, ref, tag))) - u_star

    z = float(brentq(f, grid[i], grid[i + 1], xtol=1e-14, rtol=1e-14, maxiter=200))
    return z, abs(f(z))


def hold_runs(plants: Sequence[Plant], reference: float = 1.0, hold: float = 60.0) -> list[Run]:
    """The set-point check's long step: ``reference`` for ``hold`` seconds, one per plant."""
    return [Run(p, np.full((1, int(round(hold / p.dt))), float(reference))) for p in plants]


def tail_table(
    plants: Sequence[Plant],
    trajectories: Mapping[str, Sequence[Trajectory]],
    z_end: np.ndarray | float,
    reference: float = 1.0,
    tail: float = 20.0,
) -> pd.DataFrame:
    """What is left of the motion over the holds' last ``tail`` seconds, per plant.

    ``trajectories``: per controller, the holds of :func:`hold_runs` from rest. Columns
    ``tail_error_<c>``: the tail's RMS tracking error relative to ``|reference|``;
    ``tail_du_<c>``: the tail's RMS change of control per sample (NaN: diverged);
    ``z_end_GC``: ``z_end``, the policy's error integral at the hold's end (NaN: refused).
    """
    out = pd.DataFrame({"system": [p.name for p in plants]})
    for name, trajs in trajectories.items():
        if name == "GC":  # where the policy's integral ended (one row per plant)
            out["z_end_GC"] = z_end
        errs, dus = [], []
        for p, tr in zip(plants, trajs, strict=True):
            k = int(round(tail / p.dt))
            e = (tr.r[0, -k:] - tr.y[0, -k - 1 : -1]) / abs(float(reference))
            du = np.diff(tr.u[0, -k - 1 :])
            bad = bool(tr.diverged[0])
            errs.append(np.nan if bad else float(np.sqrt(np.mean(e**2))))
            dus.append(np.nan if bad else float(np.sqrt(np.mean(du**2))))
        out[f"tail_error_{name}"], out[f"tail_du_{name}"] = errs, dus
    return out


def _radius_row(
    runtime: PolicyRuntime, policy: torch.nn.Module, plant: Plant, reference: float, z0: float
) -> tuple[object, ...]:
    """One plant's ``(system, r, z_LQI, z*, residual, radius_GC, radius_LQI)``."""
    x_star, u_star, r = equilibrium(plant, reference)
    gains = design_lqi(plant)
    z_lqi = -(u_star + float(np.dot(gains.Kx, x_star))) / float(gains.Ki)
    window = rest_window(plant, x_star, z_lqi, u_star, r, history=runtime.history,
                         controls=runtime.controls, tag=runtime.tags[plant.name])  # fmt: skip
    start = z0 if np.isfinite(z0) and r == reference else z_lqi
    z_star, resid = _integral_at(policy, window, u_star, start)
    radius_lqi = float(np.abs(np.linalg.eigvals(sampled_closed_loop(plant, gains))).max())
    if not np.isfinite(z_star):
        return plant.name, r, z_lqi, z_star, resid, np.nan, radius_lqi
    state = window[0].detach().clone()
    state[..., MAX_ORDER] = z_star
    state.requires_grad_(True)
    (grad,) = torch.autograd.grad(_control(policy, (state, *window[1:])), state)
    jac = grad[0].numpy()
    Ad, Bd = discretise(plant.A, plant.B, plant.dt)
    ju = jac[:, -1] if runtime.controls else None
    A = closed_loop_matrix(Ad, Bd, plant.C, plant.dt, jac[:, : plant.order],
                           jac[:, MAX_ORDER], ju)  # fmt: skip
    radius = float(np.abs(np.linalg.eigvals(A)).max())
    return plant.name, r, z_lqi, z_star, resid, radius, radius_lqi


def rest_radii(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    reference: float,
    ends: Sequence[float] | np.ndarray,
) -> pd.DataFrame:
    """Per plant, the spectral radii of the policy's and LQI's loops at the set point.

    Columns: ``system``, ``reference`` (0 for a nonlinear plant), ``z_LQI``, ``z_star``,
    ``residual`` (``|u(z*) - u*|``), ``radius_GC`` (NaN: no equilibrium found),
    ``radius_LQI``, ``settles`` (``radius_GC < 1``). ``ends``: per plant, where the policy's
    own hold ended (the search for ``z*`` starts there).
    """
    policy = copy.deepcopy(runtime.policy).double().eval()
    with _one_thread():
        rows = [_radius_row(runtime, policy, p, reference, float(z))
                for p, z in zip(plants, ends, strict=True)]  # fmt: skip
    cols = ["system", "reference", "z_LQI", "z_star", "residual", "radius_GC", "radius_LQI"]
    df = pd.DataFrame(rows, columns=cols)
    df["settles"] = df["radius_GC"] < 1.0
    return df


def setpoint_summary(df: pd.DataFrame) -> dict[str, object]:
    """``summary.json``'s ``setpoint`` block: the plants whose policy loop cannot settle."""
    radius = df["radius_GC"].fillna(-np.inf)
    tail = df["tail_error_GC"].fillna(np.inf)
    return {
        "unsettled": sorted(df.loc[~df["settles"], "system"].tolist()),
        "no_equilibrium": sorted(df.loc[df["radius_GC"].isna(), "system"].tolist()),
        "n_systems": int(len(df)),
        "worst_radius_GC": float(radius.max()),
        "worst_radius_system": str(df.loc[radius.idxmax(), "system"]),
        "worst_radius_LQI": float(df["radius_LQI"].max()),
        "worst_tail_error_GC": float(tail.max()),
        "worst_tail_system": str(df.loc[tail.idxmax(), "system"]),
        "worst_tail_error_LQI": float(df["tail_error_LQI"].max()),
    }
