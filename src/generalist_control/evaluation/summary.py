"""The quality-bar figures of an evaluation: divergences and worst GC/LQI ratios.

Every scenario counts; docs/evaluation.md ("The quality bar") lists the verdicts.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import pandas as pd
import yaml

from generalist_control.common.paths import conf_dir
from generalist_control.common.sections import read_section
from generalist_control.evaluation.eval_config import QualityBar
from generalist_control.evaluation.runner import CONTROLLERS, GC_ANTI_WINDUP, STEP_KINDS

__all__ = ["DEFAULT_BAR", "LEARNED", "summarise", "worst_errors"]

#: The quality bar of ``conf/evaluation/default.yaml``, for readers of evaluations that
#: have no config of their own (the ablation report).
DEFAULT_BAR: dict[str, Any] = yaml.safe_load(
    (conf_dir() / "evaluation" / "default.yaml").read_text()
)["quality_bar"]
LEARNED = ("GC", GC_ANTI_WINDUP)


def _worst(values: pd.Series, key: str, system_key: str | None = None) -> dict[str, Any]:
    """Largest value and its system; with nothing finite (all diverged): inf and None."""
    system_key = system_key or f"worst_{key.split('_')[0]}_system"
    if values.empty:
        return {f"worst_{key}": float("inf"), system_key: None}
    return {f"worst_{key}": float(values.max()), system_key: str(values.idxmax())}


def _ratio(
    means: pd.Series, scen: str, metric: str, num: str = "GC", den: str = "LQI"
) -> pd.Series:
    """Per system, ``num``'s mean metric over ``den``'s (systems where both are finite)."""
    a = means[scen][num].xs(metric, level="metric")
    b = means[scen][den].xs(metric, level="metric")
    return (a / b).dropna()


def _divergences(df: pd.DataFrame) -> dict[str, dict[str, int]]:
    out = {}
    for ctrl in [*CONTROLLERS, *sorted(set(df.controller) - set(CONTROLLERS))]:
        d = df[(df.controller == ctrl) & (df.metric == "diverged")]
        out[ctrl] = {s: int(v) for s, v in d.groupby("scenario")["value"].sum().items() if v > 0}
    return out


def _scenario_figures(df: pd.DataFrame, means: pd.Series) -> tuple[dict, dict]:
    """Worst ratios per step scenario, and worst RMSE ratio per tracking scenario."""
    steps, tracking = {}, {}
    for scen in dict.fromkeys(df.scenario):
        metrics = set(df[df.scenario == scen].metric)
        ctrls = set(df[df.scenario == scen].controller)
        if not {"GC", "LQI"} <= ctrls:
            continue
        if "ISE" in metrics and "rise_time" in metrics:
            ise, itae = _ratio(means, scen, "ISE"), _ratio(means, scen, "ITAE")
            ess = means[scen]["GC"].xs("relative_steady_state_error", level="metric").dropna()
            steps[scen] = {
                **_worst(ise, "ISE_ratio"),
                **_worst(itae, "ITAE_ratio"),
                **_worst(ess, "relative_ess_GC", "worst_relative_ess_system"),
                "n_systems": int(len(ise)),
            }
        elif "RMSE" in metrics:
            rmse = _ratio(means, scen, "RMSE")
            tracking[scen] = {**_worst(rmse, "RMSE_ratio"), "n_systems": int(len(rmse))}
    return steps, tracking


def _anti_windup(means: pd.Series, scenarios: list[str]) -> dict[str, Any]:
    """Per anti-windup scenario: the worst GC-AW/LQI-AW ISE ratio over its plants."""
    out = {}
    for scen in scenarios:
        if scen in means.index.get_level_values(0) and GC_ANTI_WINDUP in means[scen]:
            out[scen] = _worst(_ratio(means, scen, "ISE", GC_ANTI_WINDUP, "LQI-AW"), "ISE_ratio")
    return out


def _at_most(values: list[float], limit: float) -> bool | None:
    """All ``values`` at most ``limit``; None when nothing was measured."""
    return None if not values else bool(max(values) <= limit)


def worst_errors(out: Mapping[str, Any]) -> tuple[list[float], list[float]]:
    """GC's worst relative e_ss per step scenario, and the worst RMSE ratio per tracking one."""
    ratios = out["ratios"]
    ess = [ratios[s]["worst_relative_ess_GC"] for s in STEP_KINDS if s in ratios]
    return ess, [v["worst_RMSE_ratio"] for v in out["tracking"].values()]


def _quality_bar(out: Mapping[str, Any], bar: QualityBar) -> dict[str, bool | None]:
    """The bar's verdicts (None: not measured by this evaluation's scenarios)."""
    step = out["ratios"].get("step")
    ess, rmse = worst_errors(out)
    aw = [v["worst_ISE_ratio"] for v in out["anti_windup"].values()]
    return {
        "stable_everywhere": not any(out["diverged"].get(c) for c in LEARNED),
        f"ess_within_{100 * bar.relative_ess:g}pct": _at_most(ess, bar.relative_ess),
        f"ISE_ratio_le_{bar.ISE_ratio:g}": _at_most(
            [step["worst_ISE_ratio"]] if step else [], bar.ISE_ratio
        ),
        f"ITAE_ratio_le_{bar.ITAE_ratio:g}": _at_most(
            [step["worst_ITAE_ratio"]] if step else [], bar.ITAE_ratio
        ),
        f"RMSE_ratio_le_{bar.RMSE_ratio:g}": _at_most(rmse, bar.RMSE_ratio),
        "GC_AW_no_worse_than_LQI_AW": _at_most(aw, 1.0 + bar.anti_windup_tolerance),
    }


def summarise(df: pd.DataFrame, bar: QualityBar | None = None) -> dict[str, Any]:
    """Quality-bar figures: divergences, worst GC/LQI ratios per scenario, the bar itself.

    ``bar``: ``evaluation.quality_bar`` (None: :data:`DEFAULT_BAR`).
    """
    if bar is None:
        bar = read_section(QualityBar, DEFAULT_BAR, "evaluation.quality_bar")
    means = df.groupby(["scenario", "controller", "system", "metric"])["value"].mean()
    out: dict[str, Any] = {"diverged": _divergences(df)}
    out["ratios"], out["tracking"] = _scenario_figures(df, means)
    out["anti_windup"] = _anti_windup(means, list(bar.anti_windup))
    out["quality_bar"] = _quality_bar(out, bar)
    return out
