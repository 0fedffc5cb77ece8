"""Axes-level drawing of the ablation figures, shared by the report and the notebooks."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator

from generalist_control.evaluation.paper import ABLATION
from generalist_control.reports.runs import NO_RUN, NOT_AVAILABLE, SWEEPS, point_label

__all__ = [
    "draw_gate_heatmap",
    "draw_loss_curves",
    "draw_mse_bars",
    "draw_params_vs_mse",
    "fmt_value",
    "new_figure",
    "placeholder",
]

# --- drawing (Axes-level, reused by the notebooks) ---------------------------------------


def fmt_value(v: float | None) -> str:
    """Three significant digits, as the paper writes them: ``9.43e-04``, ``0.144``, ``1.35``."""
    if v is None or not np.isfinite(v):
        return NOT_AVAILABLE
    if v != 0 and abs(v) < 0.1:
        return f"{v:.2e}"
    return f"{v:.3g}" if abs(v) < 1e4 else f"{v:,.0f}"


def draw_mse_bars(ax: Axes, mse: pd.DataFrame, sweep: str) -> Axes:
    """Grouped bars of per-plant output MSE, one bar per sweep value, log y.

    Colours follow the position of the value in the sweep (as in :func:`draw_loss_curves`).
    A value without a run is listed in the legend as "no run"; a run without a score for a
    plant shows "no score" at that bar's place.
    """
    df = mse[mse["sweep"] == sweep]
    plants = list(dict.fromkeys(df["plant"]))
    values = list(dict.fromkeys(df["value"]))
    width = 0.8 / max(1, len(values))
    x = np.arange(len(plants))
    handles = []
    for i, value in enumerate(values):
        part = df[df["value"] == value].set_index("plant").reindex(plants)
        pos = x - 0.4 + width * (i + 0.5)
        label = point_label(sweep, value)
        if (part["status"] == NO_RUN).all():
            handles.append(
                Patch(facecolor="none", edgecolor=f"C{i}", hatch="//", label=f"{label} ({NO_RUN})")
            )
            continue
        handles.append(Patch(facecolor=f"C{i}", label=label))
        heights = part["mse"].to_numpy(dtype=float)
        ok = np.isfinite(heights) & (heights > 0)
        ax.bar(pos[ok], heights[ok], width, color=f"C{i}")
        for px in pos[~ok]:
            ax.text(
                px,
                0.02,
                NOT_AVAILABLE,
                ha="center",
                va="bottom",
                fontsize=7,
                rotation=90,
                color=f"C{i}",
                transform=ax.get_xaxis_transform(),
            )
    if (df["mse"] > 0).any():
        ax.set_yscale("log")
    ax.set_xticks(x, [p.replace("_", "\n") for p in plants], fontsize=8)
    ax.set_ylabel("output MSE, GC vs LQI (unit step)")
    ax.set_title(f"Closed-loop output MSE by {SWEEPS[sweep]}")
    ax.legend(handles=handles, fontsize=8)
    ax.grid(axis="y", which="both", alpha=0.3)
    return ax


def _paper_key(sweep: str, value: int, baseline: Mapping[str, int]) -> str:
    if sweep == "hidden":
        return f"d={value},M={baseline['experts']}"
    return f"d={baseline['hidden']},M={value}"


def draw_loss_curves(
    ax: Axes,
    loss: pd.DataFrame,
    sweep: str,
    values: Sequence[int] | None = None,
    paper: bool = True,
    baseline: Mapping[str, int] | None = None,
) -> Axes:
    """Training-loss curves (log y) of a sweep; the paper's final losses as dotted lines.

    Parameters
    ----------
    ax : Axes
    loss : DataFrame
        From :func:`loss_frame`.
    sweep : {"hidden", "experts"}
    values : sequence of int, optional
        The sweep's values, which fix the colours (default: the values in ``loss``); the
        paper's final loss is drawn for each, whether or not it has a run.
    paper : bool
        Draw the paper's final training losses.
    baseline : mapping, optional
        ``hidden`` and ``experts`` of the baseline (default 32 and 3).
    """
    base = {"hidden": 32, "experts": 3, **(baseline or {})}
    df = loss[loss["sweep"] == sweep]
    values = list(values) if values is not None else sorted(set(df["value"]))
    for i, value in enumerate(values):
        part = df[df["value"] == value]
        label = point_label(sweep, value) + ("" if len(part) else f" ({NO_RUN})")
        ax.plot(part["epoch"], part["train_loss"], color=f"C{i}", label=label, marker=".")
        ref = ABLATION["final_train_loss"].get(_paper_key(sweep, value, base))
        if paper and ref is not None:
            ax.axhline(ref, color=f"C{i}", ls=":", lw=1)
    if paper:
        ax.plot([], [], color="grey", ls=":", label="paper, final")
    ax.set_yscale("log")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("epoch")
    ax.set_ylabel("train/loss")
    ax.set_title(f"Training loss by {SWEEPS[sweep]}")
    ax.legend(fontsize=8)
    ax.grid(which="both", alpha=0.3)
    return ax


def draw_params_vs_mse(ax: Axes, params: pd.DataFrame) -> Axes:
    """Parameter count against mean output MSE, one labelled point per run.

    A mean over fewer plants than the others (a plant without a score) is labelled with
    the count, e.g. ``d=32,M=1 (1/2 plants)``. The paper's parameter counts are dotted.
    """
    df = params.dropna(subset=["n_parameters"])
    ax.scatter(df["n_parameters"], df["mse_mean"], zorder=3)
    most = int(df["n_plants"].max()) if len(df) else 0
    for _, row in df.iterrows():
        if np.isfinite(row["mse_mean"]):
            text = row["label"]
            if row["n_plants"] < most:
                text += f" ({row['n_plants']}/{most} plants)"
            ax.annotate(
                text,
                (row["n_parameters"], row["mse_mean"]),
                fontsize=8,
                xytext=(4, 4),
                textcoords="offset points",
            )
    for key, n in ABLATION["parameters"].items():
        ax.axvline(n, color="grey", ls=":", lw=1)
        ax.text(
            n,
            0.98,
            f" paper {key}: {n:,}",
            rotation=90,
            va="top",
            fontsize=7,
            color="grey",
            transform=ax.get_xaxis_transform(),
        )
    ax.set_xscale("log")
    if (df["mse_mean"] > 0).any():
        ax.set_yscale("log")
    ax.set_xlabel("parameters")
    ax.set_ylabel("mean output MSE")
    ax.set_title("Complexity against performance")
    ax.grid(which="both", alpha=0.3)
    return ax


def draw_gate_heatmap(ax: Axes, gates: pd.DataFrame) -> Axes:
    """Mean gate weight per plant (rows) and expert (columns), annotated in percent."""
    im = ax.imshow(gates.to_numpy(), vmin=0.0, vmax=1.0, cmap="viridis", aspect="auto")
    for (i, j), v in np.ndenumerate(gates.to_numpy()):
        ax.text(
            j,
            i,
            f"{100 * v:.0f}%",
            ha="center",
            va="center",
            fontsize=7,
            color="white" if v < 0.6 else "black",
        )
    ax.set_xticks(range(gates.shape[1]), [c.replace("expert_", "E") for c in gates.columns])
    ax.set_yticks(range(gates.shape[0]), list(gates.index), fontsize=7)
    ax.set_xlabel("expert")
    ax.set_title("Mean gate weight")
    ax.figure.colorbar(im, ax=ax, fraction=0.046)
    return ax


def new_figure(width: float, height: float, ncols: int = 1) -> tuple[Figure, list[Axes]]:
    """A figure (no pyplot state) with ``ncols`` axes in one row."""
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)  # the Agg backend, without touching pyplot's global state
    return fig, list(np.atleast_1d(fig.subplots(1, ncols)))


def placeholder(ax: Axes, text: str) -> None:
    """Write ``text`` in place of a panel that has nothing to draw."""
    ax.text(0.5, 0.5, text, ha="center", va="center", wrap=True, transform=ax.transAxes)
    ax.set_axis_off()
