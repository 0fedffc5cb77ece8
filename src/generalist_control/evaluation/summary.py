"""The quality-bar figures of an evaluation: divergences and worst GC/LQI ratios."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from generalist_control.evaluation.runner import CONTROLLERS, STEP_KINDS

__all__ = ["summarise"]


def _worst(values: pd.Series, key: str, system_key: str | None = None) -> dict[str, Any]:
    """Largest value and its system; with nothing finite (all diverged): inf and None."""
    system_key = system_key or f"worst_{key.split('_')[0]}_system"
    if values.empty:
        return {f"worst_{key}": float("inf"), system_key: None}
    return {f"worst_{key}": float(values.max()), system_key: str(values.idxmax())}


def summarise(df: pd.DataFrame) -> dict[str, Any]:
    """Quality-bar figures: divergences, worst ISE/ITAE ratios GC/LQI, worst relative e_ss."""
    mean = df.groupby(["scenario", "controller", "system", "metric"])["value"].mean()
    out: dict[str, Any] = {"diverged": {}, "ratios": {}}
    for ctrl in [*CONTROLLERS, *sorted(set(df.controller) - set(CONTROLLERS))]:
        d = df[(df.controller == ctrl) & (df.metric == "diverged")]
        out["diverged"][ctrl] = {
            s: int(v) for s, v in d.groupby("scenario")["value"].sum().items() if v > 0
        }
    for scen in ("step", "random_steps"):
        if scen not in mean.index.get_level_values(0):
            continue
        gc, lqi = mean[scen]["GC"], mean[scen]["LQI"]
        ratio = {
            k: (gc.xs(k, level="metric") / lqi.xs(k, level="metric")).dropna()
            for k in ("ISE", "ITAE")
        }
        ess = gc.xs("relative_steady_state_error", level="metric").dropna()
        out["ratios"][scen] = {
            **_worst(ratio["ISE"], "ISE_ratio"),
            **_worst(ratio["ITAE"], "ITAE_ratio"),
            **_worst(ess, "relative_ess_GC", "worst_relative_ess_system"),
            "n_systems": int(len(ratio["ISE"])),
        }
    step = out["ratios"].get("step", {})
    out["quality_bar"] = {
        "stable_everywhere": not any(out["diverged"]["GC"].get(s) for s in STEP_KINDS),
        "ess_within_1pct": all(
            out["ratios"].get(s, {}).get("worst_relative_ess_GC", np.inf) <= 0.01
            for s in STEP_KINDS
        ),
        "ISE_ratio_le_1.15": step.get("worst_ISE_ratio", np.inf) <= 1.15,
        "ITAE_ratio_le_2.0": step.get("worst_ITAE_ratio", np.inf) <= 2.0,
    }
    return out
