"""``comparison.md`` of the ablation report: the paper's Section 7 answered point by point."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import pandas as pd

from generalist_control.reports.claims import verdict_counts
from generalist_control.reports.figures import fmt_value
from generalist_control.reports.results_sections import table
from generalist_control.reports.runs import SWEEPS, RunPoint

__all__ = ["comparison_markdown"]


def _section(
    title: str, header: Sequence[str], rows: Sequence[Sequence[Any]], note: str = ""
) -> list[str]:
    """A section of the report: its heading, a note if any, its table."""
    return ["", f"## {title}", "", *([note, ""] if note else []), *table(header, rows)]


def _claims(claims: pd.DataFrame, recipe: str) -> list[str]:
    tally = ", ".join(f"{n} {v}" for v, n in verdict_counts(claims).items())
    rows = claims[["claim", "paper", "ours", "verdict", "rule", "note"]].to_numpy().tolist()
    header = ["claim", "paper", "ours (per seed)", "verdict", "rule", "note"]
    return [
        *_section(f"The paper's claims ({recipe} recipe): {tally}", header, rows),
        "",
        "A verdict needs every seed: `seed-dependent` when some seeds reproduce the figure and "
        "others do not. `not comparable`: the figures differ in definition for this recipe.",
    ]


def _runs(points: pd.DataFrame) -> list[str]:
    if points.empty:
        return []
    rows = []
    for r in points.to_dict(orient="records"):
        n_par = r.get("n_parameters")
        checked = r.get("bar_checked")
        bar = f"{int(r['bar_passed'])}/{int(checked)}" if pd.notna(checked) else "no evaluation"
        rows.append(
            [f"`{r['run']}`", f"{int(n_par):,}" if pd.notna(n_par) else "n/a",
             fmt_value(r.get("final_train_loss")), fmt_value(r.get("final_val_loss")),
             fmt_value(r.get("mse_mean")), bar, f"`{str(r['run_id'])[:8]}`"]
        )  # fmt: skip
    header = ["run", "parameters", "final train loss", "final val loss", "mean closed-loop MSE"]
    return _section("Every run", [*header, "quality bar", "MLflow run"], rows)


def _verdicts(points: pd.DataFrame) -> list[str]:
    cols = [c for c in points.columns if c.startswith("bar/")]
    if not cols:
        return []
    runs = [f"`{r}`" for r in points["run"]]
    rows = []
    for col in cols:
        cells = ["n/a" if pd.isna(v) else ("pass" if v else "**fail**") for v in points[col]]
        rows.append([f"`{col[4:]}`", *cells])
    return _section("Quality bar per run (docs/evaluation.md)", ["verdict", *runs], rows)


def _scenarios(worst: pd.DataFrame, separating: Mapping[str, str]) -> list[str]:
    if worst.empty:
        return []
    runs = list(dict.fromkeys(worst["run"]))
    rows = []
    for scen, part in worst.groupby("scenario", sort=False):
        by_run = part.set_index("run")
        cells = []
        for run in runs:
            if run not in by_run.index:
                cells.append("")
                continue
            r = by_run.loc[run]
            text = fmt_value(r["worst_ratio"])
            cells.append(text + (f", {r['GC_diverged']} diverged" if r["GC_diverged"] else ""))
        kind = "ISE" if part["kind"].iloc[0] == "step" else "RMSE"
        rows.append([f"`{scen}`", kind, *cells, "yes" if scen in separating else ""])
    title = "Scenarios: the worst plant's GC/LQI ratio per run (per-plant: `scenarios.csv`)"
    header = ["scenario", "ratio of", *[f"`{r}`" for r in runs], "separates"]
    lines = [*_section(title, header, rows), ""]
    if not separating:
        return [*lines, "No scenario separates the runs."]
    return [*lines, "Scenarios that separate the runs:", ""] + [
        f"- `{scen}`: {why}" for scen, why in separating.items()
    ]


def _gates(gates: pd.DataFrame | None, gate_run: RunPoint | None) -> list[str]:
    if gates is None or gate_run is None:
        return []
    rows = [
        [p, str(r.idxmax()).replace("expert_", ""), f"{r.max():.0%}"] for p, r in gates.iterrows()
    ]
    title = f"Gate weights of {gate_run.label} (run `{gate_run.run_id[:8]}`), every plant"
    note = (
        "Mean gate weight over a closed-loop unit step (`gate_weights.csv`, "
        "`gate_weights.png`). Expert numbers are arbitrary: compare shares, not numbers."
    )
    return _section(title, ["plant", "dominant expert", "its share"], rows, note)


def _mse_tables(runs: pd.DataFrame, points: pd.DataFrame) -> list[str]:
    """One per-plant MSE table per sweep, from ``runs.csv`` and ``points.csv``."""
    plants = [c[4:] for c in points.columns if c.startswith("mse/")]
    by_run = points.drop_duplicates("run_id").set_index("run_id")
    lines: list[str] = []
    for sweep, symbol in SWEEPS.items():
        part = runs[runs["sweep"] == sweep]
        if part.empty or not plants:
            continue
        rows = [
            [plant]
            + [
                fmt_value(by_run.loc[r.run_id, f"mse/{plant}"]) if r.status == "ok" else r.status
                for r in part.itertuples()
            ]
            for plant in plants
        ]
        title = f"Output MSE by {symbol} (figure `mse_{sweep}.png`)"
        lines += _section(title, ["plant", *part["label"]], rows)
    return lines


def comparison_markdown(
    tables: Mapping[str, Any], gates: pd.DataFrame | None, gate_run: RunPoint | None, recipe: str
) -> str:
    """The report's markdown from :func:`~generalist_control.reports.ablation.report_tables`.

    ``gates``, ``gate_run``: the M = 5 model's gate weights and run (None without it).
    """
    lines = [
        "# Ablation study (Section 7): our runs beside the paper",
        "",
        "Written by `python -m generalist_control.report` from the MLflow training runs and "
        'their evaluations. "no run": no finished run of that configuration; "no score": the '
        "run has no such figure (a diverged closed loop, a plant it was not trained on). MSE "
        "is GC against LQI, unit step, the ablation set (`closed_loop.systems`).",
        *_claims(tables["claims"], recipe),
        *_runs(tables["points"]),
        *_verdicts(tables["points"]),
        *_scenarios(tables["worst"], tables["separating"]),
        *_gates(gates, gate_run),
        *_mse_tables(tables["runs"], tables["points"]),
    ]
    return "\n".join(lines) + "\n"
