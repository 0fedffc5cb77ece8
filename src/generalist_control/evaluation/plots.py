"""Plots of the closed-loop evaluation (PNG, 80 dpi, under ``plots/``).

Per plant its step and sine sheet; per plant of a scenario on at most :data:`PER_PLANT`
plants, a figure of every controller; a scenario on more plants, one grid.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from generalist_control.simulation.simulate import Trajectory

__all__ = ["PER_PLANT", "plot_all", "pyplot"]

_STYLE = {
    "GC": ("tab:blue", "-"),
    "LQI": ("tab:orange", "--"),
    "LQI-AW": ("tab:green", ":"),
    "GC-AW": ("tab:purple", "-."),
}
_ORDER = ("GC", "GC-AW", "LQI", "LQI-AW")
_PAIR = ("GC", "LQI")  # the step and sine sheets
#: Scenarios with at most this many plants get a figure per plant, the others one grid.
PER_PLANT = 4
#: Shown in the step and sine sheets only.
_BASIC = ("step", "sine", "ramp", "composite", "random_steps")

Runs = Mapping[str, Mapping[str, Trajectory]]
Trajs = Mapping[str, Runs]


def pyplot() -> Any:
    """The pyplot of matplotlib on the Agg backend, imported on first use (half a second)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _light(ax: Any) -> None:
    """A grid and about three ticks per axis: tick labels are most of a figure's drawing."""
    ax.grid(alpha=0.3)
    ax.locator_params(nbins=3)


def _label(ctrl: str, tr: Trajectory) -> str:
    return ctrl + (" (diverged)" if tr.diverged[0] else "")


def _step_sine(trajs: Trajs, system: str, path: Path) -> None:
    """``system``'s step and sine responses (GC and LQI), output and control, into ``path``."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(10, 5.5), sharex="col")
    for col, scen in enumerate(("step", "sine")):
        ax_y, ax_u = axes[0, col], axes[1, col]
        runs = trajs.get(scen, {})
        by_ctrl = {c: runs[c][system] for c in _PAIR if system in runs.get(c, {})}
        if by_ctrl:
            first = next(iter(by_ctrl.values()))
            n = first.u.shape[1]
            ax_y.plot(first.t[:n], first.r[0], color="0.4", lw=1, label="reference")
            for c, tr in by_ctrl.items():
                color, ls = _STYLE[c]
                ax_y.plot(tr.t[:n], tr.y[0, :n], color=color, ls=ls, label=_label(c, tr))
                ax_u.plot(tr.t[:n], tr.u[0], color=color, ls=ls)
            ax_y.legend(fontsize=7)
            ax_y.set_title(f"{system}: {scen}")
        ax_y.set_ylabel("y")
        ax_u.set_ylabel("u")
        ax_u.set_xlabel("t (s)")
    for ax in axes.flat:
        _light(ax)
    # fixed margins: tight_layout doubles the drawing time
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.1, top=0.94, wspace=0.18, hspace=0.1)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _run_figure(
    runs: Mapping[str, Mapping[str, Trajectory]], scen: str, s: str, out: Path
) -> Path:
    """One plant's run of a scenario on few plants: every controller, output and control."""
    plt = pyplot()
    fig, (ax_y, ax_u) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    by_ctrl = {c: runs[c][s] for c in runs}
    ref = next(iter(by_ctrl.values()))
    n = ref.u.shape[1]
    ax_y.plot(ref.t[:n], ref.r[0], color="0.4", lw=1, label="reference")
    for ctrl in (c for c in _ORDER if c in by_ctrl):
        tr, (color, ls) = by_ctrl[ctrl], _STYLE[ctrl]
        ax_y.plot(tr.t[:n], tr.y[0, :n], color=color, ls=ls, label=_label(ctrl, tr))
        ax_u.plot(tr.t[:n], tr.u[0], color=color, ls=ls)
    ax_y.set_title(f"{s}: {scen}")
    ax_y.set_ylabel("y")
    ax_u.set_ylabel("u")
    ax_u.set_xlabel("t (s)")
    ax_y.legend(fontsize=7)
    for ax in (ax_y, ax_u):
        _light(ax)
    fig.subplots_adjust(left=0.11, right=0.97, bottom=0.1, top=0.94, hspace=0.08)
    path = out / f"{s}_{scen}.png"
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def _cell(ax: Any, by_ctrl: Mapping[str, Trajectory], at: tuple[int, int], name: str) -> None:
    """One plant's first run, scaled into the unit cell ``at`` (column, row from the top)."""
    col, row = at
    plt = pyplot()
    ref = next(iter(by_ctrl.values()))
    n = ref.u.shape[1]
    curves = {"reference": ref.r[0]} | {c: by_ctrl[c].y[0, :n] for c in _ORDER if c in by_ctrl}
    finite = np.concatenate([v[np.isfinite(v)] for v in curves.values()])
    lo, hi = (finite.min(), finite.max()) if finite.size else (0.0, 1.0)
    span = hi - lo if hi > lo else 1.0
    x = col + 0.04 + 0.92 * ref.t[:n] / max(ref.t[n - 1], 1e-12)
    for key, v in curves.items():
        color, ls = _STYLE.get(key, ("0.4", "-"))
        y = -row - 0.9 + 0.75 * (v - lo) / span
        ax.plot(x, y, color=color, ls=ls, lw=1 if key == "reference" else 1.2)
    ax.text(col + 0.04, -row - 0.06, f"{name}  [{lo:.3g}, {hi:.3g}]", fontsize=7, va="top")
    ax.add_patch(plt.Rectangle((col, -row - 1), 1, 1, fill=False, lw=0.5, ec="0.7"))


def _grid(runs: Runs, scen: str, out: Path) -> Path:
    """One cell per plant, each scaled to its curves' range, on one axes without ticks."""
    systems, plt = list(runs.get("GC", {})), pyplot()
    cols = math.ceil(math.sqrt(len(systems)))
    rows = math.ceil(len(systems) / cols)
    fig = plt.figure(figsize=(2.4 * cols, 1.7 * rows + 0.5))
    ax = fig.add_axes((0.005, 0.005, 0.99, 1 - 0.5 / (1.7 * rows + 0.5)))
    for k, s in enumerate(systems):
        _cell(ax, {c: runs[c][s] for c in runs if s in runs[c]}, (k % cols, k // cols), s)
    ax.set_xlim(0, cols)
    ax.set_ylim(-rows, 0)
    ax.set_axis_off()
    shown = [c for c in _ORDER if c in runs]
    handles = [plt.Line2D([], [], color="0.4")] + [
        plt.Line2D([], [], color=_STYLE[c][0], ls=_STYLE[c][1]) for c in shown
    ]
    fig.legend(handles, ["reference", *shown], loc="upper right", fontsize=8, ncol=len(handles))
    fig.suptitle(f"{scen}: output against time, first run per plant (range in brackets)",
                 fontsize=9, x=0.01, ha="left")  # fmt: skip
    path = out / f"{scen}.png"
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def plot_all(trajs: Trajs, out: Path, share: tuple[int, int] = (0, 1)) -> list[Path]:
    """Write the evaluation's figures (the module docstring) into ``out``; their paths.

    ``share``: ``(i, n)`` draws only every ``n``-th figure from the ``i``-th, so that ``n``
    processes draw them all (:func:`~generalist_control.evaluation.forked_shares.fork_map`).
    """
    out.mkdir(parents=True, exist_ok=True)
    i, n = share
    written = []
    for s in sorted(trajs.get("step", {}).get("GC", {}))[i::n]:
        written.append(out / f"{s}_step_sine.png")
        _step_sine(trajs, s, written[-1])
    figures: list[tuple[str, str | None]] = []  # (scenario, plant), or one grid: (scenario, None)
    for scen, runs in trajs.items():
        if scen not in _BASIC:
            few = len(runs.get("GC", {})) <= PER_PLANT
            figures += [(scen, s) for s in runs.get("GC", {})] if few else [(scen, None)]
    for scen, plant in figures[i::n]:
        runs = trajs[scen]
        written.append(
            _grid(runs, scen, out) if plant is None else _run_figure(runs, scen, plant, out)
        )
    return written
