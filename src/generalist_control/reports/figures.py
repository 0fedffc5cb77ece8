"""The ablation's figures, drawn from its tables (``runs.csv``, ``points.csv``, gate weights).

One drawing path: the report draws them into its folder from the tables it has just written,
and ``make results`` draws the same from the committed tables into ``docs/figures/``. A PNG
records the SHA-256 of its inputs and of this module, so an unchanged figure is not redrawn
(another matplotlib version would give other bytes).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter
from PIL import Image

from generalist_control.evaluation.paper import ABLATION
from generalist_control.reports.runs import NOT_AVAILABLE, SWEEPS

__all__ = [
    "INPUTS",
    "AblationTables",
    "draw_figures",
    "draw_gate_heatmap",
    "draw_losses",
    "draw_mse_bars",
    "draw_params_vs_mse",
    "figure_key",
    "figure_names",
    "fmt_value",
    "read_tables",
]

#: The tables a figure is drawn from, in a report's folder (gate_weights.csv is optional).
INPUTS = ("runs.csv", "points.csv", "gate_weights.csv")
DPI = 80
_KEY = "Description"  # the PNG text field that holds the inputs' digest


def fmt_value(v: float | None) -> str:
    """Three significant digits, as the paper writes them: ``9.43e-04``, ``0.144``, ``1.35``."""
    if v is None or not np.isfinite(v):
        return NOT_AVAILABLE
    if v != 0 and abs(v) < 0.1:
        return f"{v:.2e}"
    return f"{v:.3g}" if abs(v) < 1e4 else f"{v:,.0f}"


@dataclass(frozen=True)
class AblationTables:
    """A report's tables: the run drawn per sweep point, every run's figures, the gates.

    ``runs``: ``runs.csv`` (sweep, value, label, status, run_id, hidden, experts, ...);
    ``points``: ``points.csv`` (run_id, d, M, seed, n_parameters, final_train_loss,
    mse_mean, mse/<plant>, ...); ``gates``: ``gate_weights.csv`` (plants x expert_<i>) or
    None; ``key``: the digest of the files they were read from ("" in memory).
    """

    runs: pd.DataFrame
    points: pd.DataFrame
    gates: pd.DataFrame | None = None
    key: str = ""

    @property
    def plants(self) -> list[str]:
        """The plants of the MSE figures, in the columns' order."""
        return [c[4:] for c in self.points.columns if c.startswith("mse/")]

    def drawn(self, sweep: str | None = None) -> pd.DataFrame:
        """The rows of ``runs`` with a run (of one sweep, or of both)."""
        ok = self.runs["status"] == "ok"
        return self.runs[ok if sweep is None else ok & (self.runs["sweep"] == sweep)]

    def run(self, run_id: str) -> pd.Series:
        """The row of ``points`` of a run."""
        return self.points[self.points["run_id"] == run_id].iloc[0]


def read_tables(folder: str | Path) -> AblationTables:
    """The tables of a report's folder, with the digest of their bytes and of this module."""
    folder = Path(folder)
    digest = hashlib.sha256(Path(__file__).read_bytes())
    for name in INPUTS:
        path = folder / name
        digest.update(name.encode() + b"\0" + (path.read_bytes() if path.is_file() else b""))
    gates_csv = folder / "gate_weights.csv"
    gates = pd.read_csv(gates_csv, index_col=0) if gates_csv.is_file() else None
    return AblationTables(
        pd.read_csv(folder / "runs.csv"),
        pd.read_csv(folder / "points.csv"),
        gates if gates is not None and len(gates) else None,
        f"sha256:{digest.hexdigest()}",
    )


def draw_mse_bars(ax: Axes, t: AblationTables, sweep: str) -> Axes:
    """Grouped bars of per-plant output MSE, one bar per point of the sweep, log y.

    A run without a score for a plant (its loop diverged) shows "no score" at that bar.
    """
    plants = t.plants
    drawn = t.drawn(sweep)
    width = 0.8 / max(1, len(drawn))
    x = np.arange(len(plants))
    for i, row in enumerate(drawn.itertuples()):
        heights = t.run(row.run_id)[[f"mse/{p}" for p in plants]].to_numpy(dtype=float)
        pos = x - 0.4 + width * (i + 0.5)
        ok = np.isfinite(heights) & (heights > 0)
        ax.bar(pos[ok], heights[ok], width, color=f"C{i}", label=str(row.label))
        for px in pos[~ok]:
            ax.text(px, 0.02, NOT_AVAILABLE, ha="center", va="bottom", fontsize=6,
                    rotation=90, color=f"C{i}", transform=ax.get_xaxis_transform())  # fmt: skip
    ax.set_yscale("log")
    ax.set_xticks(x, [p.replace("_", "\n") for p in plants], fontsize=6)
    ax.set_ylabel("output MSE, GC vs LQI", fontsize=8)
    ax.set_title(f"Closed-loop output MSE by {SWEEPS[sweep]}", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(axis="y", which="both", alpha=0.3)
    return ax


def draw_losses(ax: Axes, t: AblationTables, sweep: str) -> Axes:
    """Final training loss of every run (each seed a line) at each point of the sweep.

    The paper's final losses are the black crosses.
    """
    drawn = t.drawn(sweep)
    configs = list(zip(drawn["hidden"].astype(int), drawn["experts"].astype(int), strict=True))
    x = np.arange(len(configs))
    seeds = t.points["seed"]
    for i, seed in enumerate(sorted(seeds.dropna().unique())):
        runs = t.points[seeds == seed].set_index(["d", "M"])["final_train_loss"]
        ax.plot(x, [runs.get(c, np.nan) for c in configs], "o-", color=f"C{i}",
                label=f"seed {seed:g}")  # fmt: skip
    paper = [ABLATION["final_train_loss"].get(f"d={d},M={m}", np.nan) for d, m in configs]
    ax.plot(x, paper, "kx:", label="paper")
    ax.set_yscale("log")
    ax.set_xticks(x, [str(v) for v in drawn["label"]], fontsize=8)
    ax.set_ylabel("final train/loss", fontsize=8)
    ax.set_title(f"Final training loss by {SWEEPS[sweep]}", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(which="both", alpha=0.3)
    return ax


def draw_params_vs_mse(ax: Axes, t: AblationTables) -> Axes:
    """Parameter count against mean output MSE, one labelled point per run drawn.

    A mean over fewer plants than the others is labelled with the count, ``(1/2 plants)``.
    The paper's parameter counts are dotted.
    """
    rows = [t.run(r) for r in dict.fromkeys(t.drawn()["run_id"])]
    counts = [
        int(np.isfinite(r[[f"mse/{p}" for p in t.plants]].to_numpy(float)).sum()) for r in rows
    ]
    most = max(counts, default=0)
    for row, n in zip(rows, counts, strict=True):
        text = f"d={row['d']},M={row['M']}" + (f" ({n}/{most} plants)" if n < most else "")
        ax.scatter(row["n_parameters"], row["mse_mean"], color="C0", zorder=3)
        ax.annotate(text, (row["n_parameters"], row["mse_mean"]), fontsize=7, xytext=(3, 3),
                    textcoords="offset points")  # fmt: skip
    for key, n in ABLATION["parameters"].items():
        ax.axvline(n, color="grey", ls=":", lw=1)
        ax.text(n, 0.98, f" paper {key}", rotation=90, va="top", fontsize=6, color="grey",
                transform=ax.get_xaxis_transform())  # fmt: skip
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("parameters", fontsize=8)
    ax.set_ylabel("mean output MSE", fontsize=8)
    ax.set_title("Complexity against performance", fontsize=9)
    ax.grid(which="both", alpha=0.3)
    return ax


def draw_gate_heatmap(ax: Axes, gates: pd.DataFrame) -> Axes:
    """Mean gate weight per plant (rows) and expert (columns), annotated in percent."""
    values = gates.to_numpy(dtype=float)
    im = ax.imshow(values, vmin=0.0, vmax=1.0, cmap="viridis", aspect="auto")
    for (i, j), v in np.ndenumerate(values):
        ax.text(j, i, f"{100 * v:.0f}%", ha="center", va="center", fontsize=6,
                color="white" if v < 0.6 else "black")  # fmt: skip
    ax.set_xticks(range(values.shape[1]), [c.replace("expert_", "E") for c in gates.columns])
    ax.set_yticks(range(values.shape[0]), list(gates.index), fontsize=6)
    ax.set_title(f"Mean gate weight, M = {values.shape[1]}", fontsize=9)
    ax.figure.colorbar(im, ax=ax, fraction=0.05)
    return ax


def _figure(width: float, height: float, draw: Callable[[Axes], object]) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)  # the Agg backend, without pyplot's global state
    draw(fig.subplots())
    return fig


def _gates(t: AblationTables) -> Figure:
    assert t.gates is not None
    return _figure(4.2, 1.0 + 0.2 * len(t.gates), lambda ax: draw_gate_heatmap(ax, t.gates))


#: Each figure's name and its drawing, in the order the results page shows them.
FIGURES: dict[str, Callable[[AblationTables], Figure]] = {
    "mse_hidden": lambda t: _figure(5.2, 3.0, lambda ax: draw_mse_bars(ax, t, "hidden")),
    "loss_hidden": lambda t: _figure(4.0, 3.0, lambda ax: draw_losses(ax, t, "hidden")),
    "mse_experts": lambda t: _figure(5.2, 3.0, lambda ax: draw_mse_bars(ax, t, "experts")),
    "loss_experts": lambda t: _figure(4.0, 3.0, lambda ax: draw_losses(ax, t, "experts")),
    "params_vs_mse": lambda t: _figure(4.6, 3.2, lambda ax: draw_params_vs_mse(ax, t)),
    "gate_weights": _gates,
}


def figure_names(t: AblationTables) -> list[str]:
    """The figures that have something to draw (a sweep with a run; a gate model)."""
    have = {
        f"{kind}_{sweep}" for sweep in SWEEPS if len(t.drawn(sweep)) for kind in ("mse", "loss")
    }
    if len(t.drawn()):
        have.add("params_vs_mse")
    if t.gates is not None:
        have.add("gate_weights")
    return [name for name in FIGURES if name in have]


def figure_key(path: str | Path) -> str | None:
    """The inputs' digest a PNG was drawn from (None: no such file, or no digest)."""
    try:
        with Image.open(path) as im:
            return getattr(im, "text", {}).get(_KEY)
    except (OSError, ValueError):
        return None


def draw_figures(
    src: str | Path, dest: str | Path, names: Sequence[str] | None = None
) -> list[str]:
    """Draw the figures of the tables in ``src`` into ``dest/<name>.png``; their names.

    A figure whose PNG already records these inputs is left as it is; each is written
    through a temporary sibling and a rename.
    """
    t = read_tables(src)
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    names = list(names if names is not None else figure_names(t))
    for name in names:
        path = dest / f"{name}.png"
        if figure_key(path) == t.key:
            continue
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        try:
            FIGURES[name](t).savefig(tmp, format="png", dpi=DPI, metadata={_KEY: t.key})
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
    return names
