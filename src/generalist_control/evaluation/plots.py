"""Plots of the closed-loop evaluation: step and sine responses, perturbation runs."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from generalist_control.simulation.simulate import Trajectory  # noqa: E402

__all__ = ["plot_all"]

_STYLE = {
    "GC": ("tab:blue", "-"),
    "LQI": ("tab:orange", "--"),
    "LQI-AW": ("tab:green", ":"),
    "GC-AW": ("tab:purple", "-."),
}


def _panel(ax_y, ax_u, by_ctrl: Mapping[str, Trajectory], controllers: tuple[str, ...]) -> None:
    ref = next(iter(by_ctrl.values()))
    n = ref.u.shape[1]
    ax_y.plot(ref.t[:n], ref.r[0], color="0.4", lw=1, label="reference")
    for ctrl in controllers:
        tr = by_ctrl.get(ctrl)
        if tr is None:
            continue
        color, ls = _STYLE[ctrl]
        label = ctrl + (" (diverged)" if tr.diverged[0] else "")
        ax_y.plot(tr.t[:n], tr.y[0, :n], color=color, ls=ls, label=label)
        ax_u.plot(tr.t[:n], tr.u[0], color=color, ls=ls)
    ax_y.set_ylabel("y")
    ax_u.set_ylabel("u")
    ax_u.set_xlabel("t (s)")
    ax_y.legend(fontsize=7)
    for ax in (ax_y, ax_u):
        ax.grid(alpha=0.3)


def plot_all(trajs: Mapping[str, Mapping[str, Mapping[str, Trajectory]]], out: Path) -> list[Path]:
    """Step and sine responses per plant (GC vs LQI), and each perturbation run."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    systems = sorted(trajs.get("step", {}).get("GC", {}))
    for s in systems:
        fig, axes = plt.subplots(2, 2, figsize=(10, 5.5), sharex="col")
        for col, scen in enumerate(("step", "sine")):
            by_ctrl = {
                c: trajs[scen][c][s] for c in ("GC", "LQI") if s in trajs.get(scen, {}).get(c, {})
            }
            if by_ctrl:
                _panel(axes[0, col], axes[1, col], by_ctrl, ("GC", "LQI"))
                axes[0, col].set_title(f"{s}: {scen}")
        # fixed margins: tight_layout doubles the drawing time of the evaluation's plots
        fig.subplots_adjust(left=0.08, right=0.98, bottom=0.1, top=0.94, wspace=0.18, hspace=0.1)
        path = out / f"{s}_step_sine.png"
        fig.savefig(path, dpi=80)
        plt.close(fig)
        written.append(path)
    for scen, runs in trajs.items():
        if scen in ("step", "sine", "ramp", "composite", "random_steps"):
            continue
        for s in runs.get("GC", {}):
            fig, (ax_y, ax_u) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
            order = tuple(c for c in ("GC", "GC-AW", "LQI", "LQI-AW") if c in runs)
            _panel(ax_y, ax_u, {c: runs[c][s] for c in runs}, order)
            ax_y.set_title(f"{s}: {scen}")
            fig.subplots_adjust(left=0.11, right=0.97, bottom=0.1, top=0.94, hspace=0.08)
            path = out / f"{s}_{scen}.png"
            fig.savefig(path, dpi=80)
            plt.close(fig)
            written.append(path)
    return written
