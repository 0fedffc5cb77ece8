"""The bars of the variants evaluation (issue 13) and its figures.

On the unit step, GC's ISE against each variant's own LQI (the oracle) and the nominal LQI;
a diverged run's ISE counts as infinite. docs/evaluation.md lists the bars.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.evaluation.eval_config import VariantBar
from generalist_control.evaluation.plots import pyplot

__all__ = ["ise_table", "plot_variants", "summarise_variants"]


def ise_table(df: pd.DataFrame, scenario: str) -> pd.DataFrame:
    """ISE per (system, variant) and controller on ``scenario`` (first run), inf if diverged."""
    sel = df[(df.scenario == scenario) & (df.run == 0)]
    ise = sel[sel.metric == "ISE"].pivot_table(
        index=["system", "variant"], columns="controller", values="value", dropna=False
    )
    div = sel[sel.metric == "diverged"].pivot_table(
        index=["system", "variant"], columns="controller", values="value"
    )
    ise = ise.reindex_like(div)
    out = ise.where(div == 0, np.inf)
    out["GC/LQI"] = out["GC"] / out["LQI"]
    out["LQI-nominal/LQI"] = out["LQI-nominal"] / out["LQI"]
    out["GC/LQI-nominal"] = out["GC"] / out["LQI-nominal"]
    return out


def summarise_variants(df: pd.DataFrame, scenario: str, bar: VariantBar) -> dict[str, Any]:
    """The bars (module docstring) with their figures and a verdict each, plus per plant."""
    t = ise_table(df, scenario)
    gc_div = df[(df.controller == "GC") & (df.metric == "diverged")]
    n_div = int(gc_div.value.sum())
    fewest = int(t.groupby(level="system").size().min())
    median, worst = (float(f(t["GC/LQI"].to_numpy(float))) for f in (np.median, np.max))
    bad = t[t["LQI-nominal/LQI"] > bar.nominal_worse]
    beat = float(np.median(bad["GC/LQI-nominal"])) if len(bad) else None
    bars: dict[str, dict[str, Any]] = {
        "no_divergence": {"GC_diverged_runs": n_div, "pass": n_div == 0},
        "variants_per_plant": {
            "min": fewest,
            "limit": bar.min_variants,
            "pass": fewest >= bar.min_variants,
        },
        "median_ISE_ratio": {
            "value": median,
            "limit": bar.median_ISE_ratio,
            "pass": median <= bar.median_ISE_ratio,
        },
        "worst_ISE_ratio": {
            "value": worst,
            "limit": bar.worst_ISE_ratio,
            "pass": worst <= bar.worst_ISE_ratio,
        },
        "beats_nominal": {
            "variants": len(bad),
            "nominal_worse_than": bar.nominal_worse,
            "median_GC_over_nominal": beat,
            "pass": None if beat is None else beat < 1.0,
        },
    }
    verdicts = [v["pass"] for v in bars.values() if v["pass"] is not None]
    per_plant = {
        str(name): {
            "variants": int(len(g)),
            "median_GC_over_oracle": float(g["GC/LQI"].median()),
            "worst_GC_over_oracle": float(g["GC/LQI"].max()),
            "median_nominal_over_oracle": float(g["LQI-nominal/LQI"].median()),
        }
        for name, g in t.groupby(level="system")
    }
    diverged = df[df.metric == "diverged"].groupby(["controller", "scenario"]).value.sum()
    return {
        "scenario": scenario,
        "bars": bars,
        "pass": all(verdicts),
        "per_plant": per_plant,
        "ratios": {"variants": {k: v["value"] for k, v in bars.items() if "value" in v}},
        "diverged": {
            c: {s: int(n) for (c2, s), n in diverged.items() if c2 == c}
            for c in df.controller.unique()
        },
    }


def plot_variants(df: pd.DataFrame, scenario: str, out_dir: Path) -> list[Path]:
    """Two figures: ISE ratios per plant, and GC/oracle against nominal/oracle."""
    out_dir.mkdir(parents=True, exist_ok=True)
    t = ise_table(df, scenario).replace(np.inf, np.nan)
    names = sorted(t.index.get_level_values("system").unique())
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 4))
    for i, name in enumerate(names):
        g = t.loc[name]
        ax.scatter(np.full(len(g), i - 0.12), g["GC/LQI"], s=12, c="tab:blue")
        ax.scatter(np.full(len(g), i + 0.12), g["LQI-nominal/LQI"], s=12, c="tab:orange")
    ax.scatter([], [], c="tab:blue", label="GC / oracle LQI")
    ax.scatter([], [], c="tab:orange", label="nominal LQI / oracle LQI")
    ax.axhline(1.0, color="0.5", lw=0.8)
    ax.set_yscale("log")
    ax.set_xticks(range(len(names)), names, rotation=70, fontsize=7)
    ax.set_ylabel(f"ISE ratio ({scenario})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths = [out_dir / "ise_ratio_per_plant.png"]
    fig.savefig(paths[0], dpi=120)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.scatter(t["LQI-nominal/LQI"], t["GC/LQI"], s=12)
    lim = [0.8, max(2.0, float(np.nanmax(t[["GC/LQI", "LQI-nominal/LQI"]].to_numpy())) * 1.1)]
    ax.plot(lim, lim, color="0.5", lw=0.8, label="GC = nominal LQI")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("ISE nominal LQI / oracle LQI")
    ax.set_ylabel("ISE GC / oracle LQI")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / "gc_vs_nominal.png")
    fig.savefig(paths[1], dpi=120)
    plt.close(fig)
    return paths
