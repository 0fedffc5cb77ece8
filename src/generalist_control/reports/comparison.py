"""The ablation figures beside the paper's (``comparison.md`` of the report)."""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import pandas as pd

from generalist_control.evaluation.paper import ABLATION
from generalist_control.reports.figures import fmt_value
from generalist_control.reports.runs import (
    NO_RUN,
    NOT_AVAILABLE,
    SWEEPS,
    RunPoint,
    point_label,
    unique_points,
)

__all__ = ["comparison_markdown"]


def _parse_key(key: str) -> tuple[int, int]:
    m = re.fullmatch(r"d=(\d+),M=(\d+)", key)
    if not m:
        raise ValueError(f"unexpected configuration key '{key}'")
    return int(m.group(1)), int(m.group(2))


def _fmt_run(p: RunPoint | None) -> str:
    return f"`{p.run_id[:8]}`" if p else ""


def _paper_rows(by_cfg: Mapping[tuple[int, int], RunPoint]) -> list[str]:
    """Rows of the paper's final losses, parameter counts and per-plant MSEs beside ours."""

    def find(key: str) -> RunPoint | None:
        return by_cfg.get(_parse_key(key))

    lines = []
    for key, ref in ABLATION["final_train_loss"].items():
        p = find(key)
        ours = NO_RUN if p is None else fmt_value(p.train_loss)
        lines.append(
            f"| final training loss | {key} | {fmt_value(ref)} | {ours} | {_fmt_run(p)} |"
        )
    for key, ref in ABLATION["parameters"].items():
        p = find(key)
        ours = (
            NO_RUN if p is None else (f"{p.n_parameters:,}" if p.n_parameters else NOT_AVAILABLE)
        )
        approx = "" if key == "d=32,M=3" else "≈"
        lines.append(f"| parameters | {key} | {approx}{ref:,} | {ours} | {_fmt_run(p)} |")
    for name, plant in (("crazyflie_mse", "crazyflie_altitude"), ("hvac_mse", "hvac_two_zone")):
        for key, ref in ABLATION[name].items():
            p = find(key)
            ours = NO_RUN if p is None else fmt_value(p.mse.get(plant))
            lines.append(f"| {plant} MSE | {key} | {fmt_value(ref)} | {ours} | {_fmt_run(p)} |")
    return lines


def _gate_rows(gates: pd.DataFrame | None, gate_run: RunPoint | None) -> list[str]:
    """Rows of the paper's dominant gate weights beside ours."""
    gate_cfg = gate_run.label if gate_run else "d=32,M=5"  # the paper's gate model
    lines = []
    for plant, ref in ABLATION["gate_weights_m5"].items():
        ((expert, weight),) = ref.items()
        paper = f"{expert.replace('_', ' ')}: {weight:.0%}"
        if gates is None or gate_run is None:
            ours = NO_RUN
        elif plant not in gates.index:
            ours = "not trained on it"
        else:
            row = gates.loc[plant]
            ours = f"{row.idxmax().replace('_', ' ')}: {row.max():.0%} (dominant)"
        lines.append(
            f"| gate weight, {plant} | {gate_cfg} | {paper} | {ours} | {_fmt_run(gate_run)} |"
        )
    return lines


def _mse_tables(mse: pd.DataFrame) -> list[str]:
    """One per-plant MSE table per sweep."""
    lines: list[str] = []
    for sweep, symbol in SWEEPS.items():
        part = mse[mse["sweep"] == sweep]
        if part.empty:
            continue
        values = list(dict.fromkeys(part["value"]))
        lines += [
            "",
            f"## Output MSE by {symbol} (figure `mse_{sweep}.png`)",
            "",
            "| plant | " + " | ".join(point_label(sweep, v) for v in values) + " |",
            "| --- |" + " --- |" * len(values),
        ]
        for plant, rows in part.groupby("plant", sort=False):
            cells = []
            for v in values:
                r = rows[rows["value"] == v].iloc[0]
                cells.append(fmt_value(r["mse"]) if r["status"] == "ok" else r["status"])
            lines.append(f"| {plant} | " + " | ".join(cells) + " |")
    return lines


def comparison_markdown(
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    mse: pd.DataFrame,
    gates: pd.DataFrame | None,
    gate_run: RunPoint | None,
    eval_summary: Mapping[str, Any] | None = None,
) -> str:
    """Markdown: our ablation figures beside the paper's, and the per-plant MSE tables."""
    by_cfg = {(p.hidden, p.experts): p for p in unique_points(sweeps)}
    lines = [
        "# Ablation study (Section 7): our runs beside the paper",
        "",
        "Redrawn from the MLflow training runs by `python -m generalist_control.report`. "
        '"no run": no finished run of that configuration; "no score": the run has no score '
        "(diverged, or not trained on the plant). Our training loss is the MSE on normalised "
        "controls (see docs/training.md); MSE is GC against LQI, unit step, ablation set.",
        "",
        "| quantity | configuration | paper | ours | run |",
        "| --- | --- | --- | --- | --- |",
        *_paper_rows(by_cfg),
        *_gate_rows(gates, gate_run),
    ]
    lines += [
        "",
        "Expert numbering is arbitrary (any permutation of the experts is the same model), so "
        "for the gate weights compare the dominant expert's share, not its index.",
    ]
    lines += _mse_tables(mse)
    if eval_summary:
        qb = eval_summary.get("quality_bar", {})
        lines += [
            "",
            "## The pipeline's model (evaluate stage, reports/eval/summary.json)",
            "",
            "| quality bar | met |",
            "| --- | --- |",
            *[f"| {k} | {v} |" for k, v in qb.items()],
        ]
    return "\n".join(lines) + "\n"
