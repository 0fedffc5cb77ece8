"""When a diverged GC run left its expert: early (identification) or after a later change.

A policy without its tag must infer the plant from the history its own controls produce.
If it cannot, its runs leave the expert within the first seconds; if it can but its window
forgets, they leave after a later change of the reference, from a quiet state.
:func:`departure_table` tells the two apart on the evaluation's own trajectories: for every
diverged GC run, the first sample at which the GC tracking error exceeds ``factor`` times
the largest tracking error of the LQI expert on the same run (a non-finite output counts),
or, if the output never does, the sample at which the run diverged through another state,
and, for a piecewise-constant reference, how many level changes came before it and how long
after the last one it left.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pandas as pd

from generalist_control.simulation.simulate import Trajectory

__all__ = ["COLUMNS", "departure_summary", "departure_table"]

COLUMNS = ["system", "scenario", "run", "t_leave", "level", "t_since_change"]

#: A reference that changes on more than this share of its samples is not a staircase.
CONTINUOUS_SHARE = 0.1


def _leave(gc: np.ndarray, lqi: np.ndarray, r: np.ndarray, factor: float) -> int:
    """First sample where ``|y_GC - r|`` exceeds ``factor`` times LQI's largest error."""
    err = np.abs(gc - r)
    bad = ~np.isfinite(err) | (err > factor * np.nanmax(np.abs(lqi - r)) + 1e-12)
    return int(np.argmax(bad)) if bad.any() else len(err) - 1


def _diverged_at(x: np.ndarray) -> int:
    """Sample a diverged run stopped at: the simulator freezes its state from there on."""
    moved = np.flatnonzero(np.any(x[1:] != x[:-1], axis=1))
    return int(moved[-1]) + 1 if len(moved) else 0


def _row(
    system: str, scenario: str, run: int, gc: Trajectory, lqi: Trajectory, factor: float
) -> list:
    """One diverged run's departure (see :func:`departure_table`)."""
    r = gc.r[run]
    k = min(_leave(gc.y[run, :-1], lqi.y[run, :-1], r, factor), _diverged_at(gc.x[run]))
    dt = float(gc.t[1] - gc.t[0])
    changes = np.flatnonzero(np.diff(r) != 0) + 1
    if len(changes) > CONTINUOUS_SHARE * len(r):
        return [system, scenario, run, k * dt, np.nan, np.nan]
    before = changes[changes <= k]
    since = k - (before[-1] if len(before) else 0)
    return [system, scenario, run, k * dt, float(len(before)), since * dt]


def departure_table(
    trajectories: Mapping[str, Mapping[str, Mapping[str, Trajectory]]],
    factor: float = 3.0,
    controller: str = "GC",
) -> pd.DataFrame:
    """Where each diverged run of ``controller`` left the LQI expert.

    Parameters
    ----------
    trajectories : mapping
        ``trajectories[scenario][controller][system]``, as
        :func:`~generalist_control.evaluation.runner.evaluate` returns them (the LQI runs
        share the GC runs' references and initial states).
    factor : float
        A run has left its expert where its tracking error first exceeds ``factor`` times
        the expert's largest tracking error on the same run, or where it diverged if that
        comes first (a state other than the output can leave first).
    controller : str

    Returns
    -------
    DataFrame
        :data:`COLUMNS`: ``t_leave`` (s from the start), ``level`` (level changes of the
        reference before it; 0 = still on the first level) and ``t_since_change`` (s since
        the last change, or since the start); both NaN for a continuously varying reference.
    """
    rows = []
    for scenario, by_ctrl in trajectories.items():
        if controller not in by_ctrl or "LQI" not in by_ctrl:
            continue
        for system, tr in by_ctrl[controller].items():
            lqi = by_ctrl["LQI"][system]
            rows += [
                _row(system, scenario, int(i), tr, lqi, factor)
                for i in np.flatnonzero(tr.diverged)
            ]
    return pd.DataFrame(rows, columns=COLUMNS)


def departure_summary(table: pd.DataFrame) -> dict[str, float | int]:
    """Counts for ``bar.json``: runs that left on their first level or after a change."""
    stepped = table.dropna(subset=["level"])
    return {
        "runs": len(table),
        "on_first_level": int((stepped.level == 0).sum()),
        "after_a_later_change": int((stepped.level > 0).sum()),
        "continuous_reference": int(table.level.isna().sum()),
        "median_t_leave_s": float(table.t_leave.median()) if len(table) else float("nan"),
    }
