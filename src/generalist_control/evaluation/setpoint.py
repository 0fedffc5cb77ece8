"""Does the policy settle at its set point? Its closed loop linearised there.

LQI's sampled loop is stable by design. A learned policy imitates the law along the data's
trajectories, but nothing forces its loop to be stable in the small where it should rest:
at the set point. If it is not, the policy cannot settle there; float rounding alone starts
a growing oscillation that only the network's nonlinearity bounds (a limit cycle), and an
actuator limit can turn it into a large one. :func:`setpoint_stability` measures it.

For each plant, at the equilibrium of a constant reference ``r``: the plant's state ``x*``
and control ``u*`` (``(Ad - I) x* + Bd u* = 0``, ``C x* = r`` for a linear plant; for a
nonlinear plant its operating point, ``r = 0``, where ``A``, ``B`` are its linearisation),
and the error integral ``z*`` at which the policy's control is ``u*`` (the root nearest
where the policy's own long hold ended, else nearest LQI's integral at rest: a grid refined
by Brent's method, as the network need not be monotone in ``z``). With every sample of the
window at that equilibrium, the derivative of the policy's first control with respect to
every window entry (automatic differentiation, in float64) closes a linear loop with the
plant sampled at ``dt`` (zero-order hold): the state is the window (the ``history`` newest
plant states, error integrals ``z_(k+1) = z_k + dt (r - C x_k)`` as the runtime keeps them,
and previous controls with the ``previous_control`` channel). Its spectral radius is below 1
exactly when small deviations die out; beside it, the radius of the plant's LQI loop
sampled the same way (:func:`~generalist_control.simulation.lqi.sampled_closed_loop`).
"""

from __future__ import annotations

import copy
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager

import numpy as np
import pandas as pd
import torch
from scipy.optimize import brentq

from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.rest_loop import closed_loop_matrix, equilibrium, rest_window
from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.lqi import LQIController, design_lqi, sampled_closed_loop
from generalist_control.simulation.simulate import PerPlantController, Run, Trajectory, discretise
from generalist_control.simulation.stacked import Segment, controller_rows, simulate_stacked

__all__ = [
    "check_hold",
    "closed_loop_matrix",
    "equilibrium",
    "hold_runs",
    "hold_tail",
    "rest_radii",
    "setpoint_stability",
    "setpoint_summary",
    "tail_table",
]


@contextmanager
def _one_thread() -> Iterator[None]:
    """Torch on one thread while the check's small float64 forwards run.

    One window, or a few hundred: more threads only wait on each other (ten times slower
    on a busy machine). The numbers are the same.
    """
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
    """The error integral nearest ``z0`` at which the control is ``u_star``: ``(z*, residual)``.

    The network need not be monotone in ``z``: the residual is tabulated on ``points``
    integrals within ``+-max(1, |z0|)`` of ``z0`` and the sign change nearest ``z0`` is
    refined by Brent's method. None: ``(nan, smallest |residual| seen)``.
    """
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
    """The long step of :func:`hold_tail`: ``reference`` for ``hold`` seconds, one per plant."""
    return [Run(p, np.full((1, int(round(hold / p.dt))), float(reference))) for p in plants]


def check_hold(hold: float, tail: float) -> None:
    """Refuse a tail that is not inside the hold."""
    if not 0.0 < tail < hold:
        raise ValueError(f"need 0 < tail < hold; got tail={tail}, hold={hold}")


def tail_table(
    plants: Sequence[Plant],
    trajectories: Mapping[str, Sequence[Trajectory]],
    z_end: np.ndarray | float,
    reference: float = 1.0,
    tail: float = 20.0,
) -> pd.DataFrame:
    """:func:`hold_tail`'s table from the holds' trajectories (per controller, per plant).

    ``z_end``: the policy's error integral at the end of each plant's hold (NaN: unknown).
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


def hold_tail(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    reference: float = 1.0,
    hold: float = 60.0,
    tail: float = 20.0,
) -> pd.DataFrame:
    """A long step from rest; what is left of the motion over its last ``tail`` seconds.

    GC and LQI hold the reference ``reference`` for ``hold`` seconds on every plant.
    Columns ``tail_error_<c>``: the RMS tracking error over the tail relative to
    ``|reference|``; ``tail_du_<c>``: the RMS change of the control from sample to sample
    over the tail (zero once a loop rests); NaN for a diverged run. ``z_end_GC``: the
    policy's error integral at the end of its hold (NaN for a plant whose run the runtime
    refused). The evaluation runs these holds in its own loop
    (:func:`~generalist_control.evaluation.runner.run_suite`).
    """
    check_hold(hold, tail)
    runs = hold_runs(plants, reference, hold)
    gc = RuntimeAdapter(runtime)
    segments = [Segment(gc, runs), Segment(PerPlantController(LQIController), runs)]
    gc_trajs, lqi_trajs = simulate_stacked(segments)
    rows = [sl.start for sl in controller_rows(segments)[0]]
    return tail_table(plants, {"GC": gc_trajs, "LQI": lqi_trajs}, gc.z_end[rows], reference, tail)


def _radius_row(
    runtime: PolicyRuntime, policy: torch.nn.Module, plant: Plant, reference: float, z0: float
) -> tuple[object, ...]:
    """One plant's ``(system, r, z_LQI, z*, residual, radius_GC, radius_LQI)``.

    ``z*`` is searched nearest ``z0`` (where the policy's own hold ended), else nearest LQI's.
    """
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

    ``ends``: per plant, the error integral at which the policy's own hold ended (NaN:
    unknown); the search for ``z*`` starts there. The columns of :func:`setpoint_stability`
    up to ``settles``.
    """
    policy = copy.deepcopy(runtime.policy).double().eval()
    with _one_thread():
        rows = [_radius_row(runtime, policy, p, reference, float(z))
                for p, z in zip(plants, ends, strict=True)]  # fmt: skip
    cols = ["system", "reference", "z_LQI", "z_star", "residual", "radius_GC", "radius_LQI"]
    df = pd.DataFrame(rows, columns=cols)
    df["settles"] = df["radius_GC"] < 1.0
    return df


def setpoint_stability(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    reference: float = 1.0,
    hold: float = 60.0,
    tail: float = 20.0,
    held: pd.DataFrame | None = None,
) -> pd.DataFrame:
    """Per plant: the spectral radius of the policy's and LQI's loops at the set point.

    Columns: ``system``, ``reference`` (``r``; 0 for a nonlinear plant), ``z_LQI`` (the
    expert's integral at rest), ``z_star`` (the policy's: for a linear plant the root
    nearest the integral at which its own hold ended, ``z_end_GC``; else nearest ``z_LQI``),
    ``residual`` (``|u(z*) - u*|``), ``radius_GC`` (NaN: no equilibrium near where the
    search started), ``radius_LQI``, ``settles`` (``radius_GC < 1``), then :func:`hold_tail`'s
    columns for ``hold`` and ``tail`` (``held``: that table, already computed). See the
    module docstring.

    Raises
    ------
    ValueError
        If the policy does not integrate the tracking error (no ``integral`` channel):
        without it a constant window need not be an equilibrium.
    """
    if not runtime.integral:
        raise ValueError(
            "the set-point check needs a policy with the integral channel (model.channels; its "
            "equilibrium is the error integral at which its control holds the plant at rest)"
        )
    if held is None:
        held = hold_tail(runtime, plants, reference, hold, tail)
    ends = held["z_end_GC"].to_numpy(dtype=float)
    return rest_radii(runtime, plants, reference, ends).merge(held, on="system")


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
