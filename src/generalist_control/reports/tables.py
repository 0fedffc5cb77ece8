"""The ablation report's tables, from the drawn runs, every seed's runs and the evaluations.

:func:`inputs_from_config` gathers what the report reads besides the drawn runs
(:class:`Inputs`: each point's evaluation, the recipe, the tolerances, the quality bar);
:func:`report_tables` makes every frame :mod:`generalist_control.reports.ablation` writes.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import DictConfig

from generalist_control.common.configs import as_dict
from generalist_control.reports import evaluations as evals
from generalist_control.reports.claims import judge_claims
from generalist_control.reports.points import infer_recipe, points_frame, run_label
from generalist_control.reports.runs import (
    RunPoint,
    loss_frame,
    mse_frame,
    params_frame,
    unique_points,
)

__all__ = ["Inputs", "inputs_from_config", "report_tables"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Inputs:
    """What the report reads besides the drawn runs, all optional.

    Attributes
    ----------
    by_config : mapping
        (d, M) -> its runs, one per seed (default: the drawn run of each).
    evaluations : mapping
        Run id -> its evaluation (:func:`.evaluations.load_evaluations`).
    recipe : str or None
        ``default`` or ``paper``; None: inferred from the runs' params.
    tolerance : mapping
        The claims' tolerances (``report.claims``).
    bar : mapping
        The quality bar's limits (``evaluation.quality_bar``), for the separating scenarios.
    eval_summary : mapping or None
        The pipeline model's evaluation summary, quoted at the end of ``comparison.md``.
    """

    by_config: Mapping[tuple[int, int], Sequence[RunPoint]] | None = None
    evaluations: Mapping[str, evals.Evaluation] = field(default_factory=dict)
    recipe: str | None = None
    tolerance: Mapping[str, float] = field(default_factory=dict)
    bar: Mapping[str, Any] = field(default_factory=dict)
    eval_summary: Mapping[str, Any] | None = None


def report_tables(
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    plants: Sequence[str],
    client: Any,
    gates: pd.DataFrame | None,
    inputs: Inputs,
) -> dict[str, Any]:
    """Every frame the report writes, from the drawn runs, every seed and the evaluations."""
    by_config = inputs.by_config or {(p.hidden, p.experts): [p] for p in unique_points(sweeps)}
    runs = [p for group in by_config.values() for p in group]
    recipe = inputs.recipe or infer_recipe(runs)
    labels = {p.run_id: run_label(p) for p in sorted(runs, key=lambda p: (p.hidden, p.experts))}
    worst = evals.scenario_worst(labels, inputs.evaluations)
    return {
        "mse": mse_frame(sweeps, plants),
        "loss": loss_frame(sweeps, client),
        "params": params_frame(sweeps, plants),
        "points": points_frame(by_config, plants, inputs.evaluations),
        "claims": judge_claims(by_config, gates, recipe, inputs.tolerance),
        "scenarios": evals.scenario_scores(labels, inputs.evaluations),
        "worst": worst,
        "separating": evals.separating(worst, inputs.bar),
        "recipe": recipe,
        "labels": labels,
    }


def inputs_from_config(
    cfg: DictConfig, by_config: Mapping[tuple[int, int], Sequence[RunPoint]]
) -> Inputs:
    """The report's other inputs from the config: evaluations, recipe, tolerances, bar."""
    rcfg = cfg.report
    eval_summary = None
    summary_path = Path(cfg.paths.get("reports_dir", "reports/eval")) / "summary.json"
    if summary_path.is_file():
        eval_summary = json.loads(summary_path.read_text())
    evaluations = evals.load_evaluations(rcfg.get("evaluations_dir"))
    if rcfg.get("evaluations_dir") and not evaluations:
        log.warning("no evaluation under %s: the report has no verdicts", rcfg.evaluations_dir)
    return Inputs(
        by_config=by_config,
        evaluations=evaluations,
        recipe=rcfg.get("recipe"),
        tolerance=as_dict(rcfg.get("claims") or {}),
        bar=as_dict((cfg.get("evaluation") or {}).get("quality_bar") or {}),
        eval_summary=eval_summary,
    )
