"""Tables of the closed-loop evaluation: the paper's Table 2 layout, every plant, recipes."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.evaluation.paper import TABLE2, TABLE2_COLUMNS, TABLE2_METRICS
from generalist_control.evaluation.summary import summarise
from generalist_control.simulation.simulate import Trajectory

__all__ = [
    "recipes_markdown",
    "scenarios_markdown",
    "responses_csv",
    "table2_markdown",
    "table_all_markdown",
]


def _fmt(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"


def _step_means(df: pd.DataFrame, scenario: str = "step") -> pd.Series:
    d = df[df.scenario == scenario]
    return d.groupby(["controller", "system", "metric"])["value"].mean()


def _table(head: list[str], rows: list[list[str]], rule: str = "---:") -> list[str]:
    """Markdown table lines: the first column left-aligned, the others ``rule``."""
    return [f"| {' | '.join(r)} |" for r in (head, ["---"] + [rule] * (len(head) - 1), *rows)]


def _worst_random_ess(gc: pd.DataFrame) -> pd.Series:
    """Per system, GC's worst relative steady-state error over the random steps."""
    rel = gc[(gc.scenario == "random_steps") & (gc.metric == "relative_steady_state_error")]
    return rel.groupby("system")["value"].max()


def table2_markdown(df: pd.DataFrame) -> str:
    """The paper's Table 2 layout for the paper systems present: paper values beside ours."""
    means = _step_means(df)
    systems = [s for s in TABLE2_COLUMNS if ("GC", s, "ISE") in means.index]
    if not systems:
        return "No system of the paper's Table 2 was evaluated.\n"
    rows = []
    for metric, symbol in TABLE2_METRICS.items():
        for ctrl in ("LQI", "GC"):
            ours = [
                "diverged"
                if means.get((ctrl, s, "diverged"), 0) > 0
                else _fmt(means.get((ctrl, s, metric), np.nan))
                for s in systems
            ]
            rows.append(
                [f"{symbol} ({ctrl}) paper", *(_fmt(TABLE2[ctrl][s][metric]) for s in systems)]
            )
            rows.append([f"{symbol} ({ctrl}) ours", *ours])
    lines = [
        "# Unit-step metrics: the paper's Table 2 beside ours",
        "",
        "Unit step from rest, dt = 0.05 s. *paper*: Agyei & Sarhadi 2026, Table 2. "
        "A diverged run shows as `diverged`.",
        "",
        *_table(["Metric", *(TABLE2_COLUMNS[s] for s in systems)], rows),
    ]
    return "\n".join(lines) + "\n"


def table_all_markdown(df: pd.DataFrame) -> str:
    """Every plant: GC and LQI unit-step metrics, ratios, and random-step results."""
    means, rnd = _step_means(df), _step_means(df, "random_steps")
    head = ["system", *(f"{c} GC/LQI" for c in TABLE2_METRICS.values()), "ISE ratio"]
    head += ["ITAE ratio", "random: ISE ratio", "random: max rel. e_ss GC", "diverged GC"]
    gc = df[df.controller == "GC"]
    div = gc[gc.metric == "diverged"].groupby("system")["value"].sum()
    rel = _worst_random_ess(gc)
    rows = []
    for s in sorted(df.system.unique()):

        def get(c: str, m: str, src: pd.Series = means, s: str = s) -> float:
            return src.get((c, s, m), np.nan)

        cells = [f"{_fmt(get('GC', m))} / {_fmt(get('LQI', m))}" for m in TABLE2_METRICS]
        cells += [_fmt(get("GC", k) / get("LQI", k)) for k in ("ISE", "ITAE")]
        cells.append(_fmt(get("GC", "ISE", rnd) / get("LQI", "ISE", rnd)))
        rows.append([s, *cells, _fmt(rel.get(s, np.nan)), str(int(div.get(s, 0)))])
    title = "# Unit-step and random-step metrics, all plants (GC / LQI)"
    return "\n".join([title, "", *_table(head, rows)]) + "\n"


def recipes_markdown(results: Mapping[str, pd.DataFrame]) -> str:
    """Per plant, the quality-bar figures of evaluations side by side (label -> metrics)."""
    labels = list(results)
    head = ["system"]
    for what in ("ISE ratio", "ITAE ratio", "e_ss (rel.)", "random: worst rel. e_ss", "diverged"):
        head += [f"{what} {label}" for label in labels]
    per: dict[str, dict[str, pd.Series]] = {}
    for label, df in results.items():
        gc, means = df[df.controller == "GC"], _step_means(df)
        step_rel = gc[(gc.scenario == "step") & (gc.metric == "relative_steady_state_error")]
        div = gc[(gc.metric == "diverged") & gc.scenario.isin(["step", "random_steps"])]
        ours = means.get("GC", pd.Series(dtype=float))
        per[label] = {
            m: ours.xs(m, level="metric") / means["LQI"].xs(m, level="metric")
            for m in ("ISE", "ITAE")
        } | {
            "ess": step_rel.groupby("system")["value"].mean(),
            "rnd": _worst_random_ess(gc),
            "div": div.groupby("system")["value"].sum(),
        }
    rows = []
    for s in sorted(set().union(*(set(df.system) for df in results.values()))):
        cells = [s]
        for key in ("ISE", "ITAE", "ess", "rnd", "div"):
            for label in labels:
                v = per[label][key].get(s, np.nan)
                cells.append(str(int(v)) if key == "div" else _fmt(v))
        rows.append(cells)
    return "\n".join(_table(head, rows)) + "\n"


def responses_csv(trajs: Mapping[str, Mapping[str, Mapping[str, Trajectory]]]) -> pd.DataFrame:
    """Unit-step responses in long form (DVC plots): system, controller, t, r, y, u."""
    frames = []
    for ctrl, by_system in trajs.get("step", {}).items():
        for system, tr in by_system.items():
            n = tr.u.shape[1]
            cols = {"t": tr.t[:n], "r": tr.r[0], "y": tr.y[0, :n], "u": tr.u[0]}
            frames.append(pd.DataFrame({"system": system, "controller": ctrl, **cols}))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _scenario_cell(summary: Mapping[str, Any], scen: str) -> str:
    """``ratio (system)`` of one scenario: ISE for step scenarios, RMSE for tracking ones."""
    div = sum(summary["diverged"].get(c, {}).get(scen, 0) for c in ("GC", "GC-AW"))
    if scen in summary["ratios"]:
        v, s = (summary["ratios"][scen][f"worst_ISE_{k}"] for k in ("ratio", "system"))
    elif scen in summary["tracking"]:
        v, s = (summary["tracking"][scen][f"worst_RMSE_{k}"] for k in ("ratio", "system"))
    else:
        return "n/a"
    cell = f"{v:.4g} ({s})" if s else "n/a"
    return cell + (f", **{div} diverged**" if div else "")


def scenarios_markdown(results: Mapping[str, pd.DataFrame]) -> str:
    """Per scenario, each evaluation's worst GC/LQI ratio and its GC divergences.

    Step scenarios give the ISE ratio, tracking scenarios the RMSE ratio (mean over a
    plant's runs, worst plant); ``results`` maps a label to an evaluation's ``metrics.csv``.
    """
    summaries = {label: summarise(df) for label, df in results.items()}
    scenarios = list(dict.fromkeys(s for df in results.values() for s in df.scenario))
    labels = list(results)
    rows = []
    for scen in scenarios:
        tracking = any(scen in s["tracking"] for s in summaries.values())
        measure = "worst RMSE ratio" if tracking else "worst ISE ratio"
        rows.append([f"`{scen}`", measure, *(_scenario_cell(summaries[k], scen) for k in labels)])
    bars = list(dict.fromkeys(k for s in summaries.values() for k in s["quality_bar"]))
    for key in bars:
        cells = [str(summaries[label]["quality_bar"].get(key)) for label in labels]
        rows.append(["quality bar", f"`{key}`", *cells])
    return "\n".join(_table(["scenario", "measure", *labels], rows, "---")) + "\n"
