"""The ablation report (paper, Section 7), redrawn from the finished MLflow training runs.

Nothing is trained here: the tables come from the runs and their evaluations, the figures from
the tables (:mod:`.figures`, as ``make results`` draws them); docs/pipeline.md lists the files.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import pandas as pd
import torch

from generalist_control.common.atomic import (
    check_replaceable,
    publish_directory,
    staging_directory,
)
from generalist_control.common.jsonsafe import finite, write_json
from generalist_control.common.secrets import redact
from generalist_control.evaluation.eval_run import RUN_TYPE_TAG
from generalist_control.reports import evaluations as evals
from generalist_control.reports.claims import judge_claims, verdict_counts
from generalist_control.reports.comparison_markdown import comparison_markdown
from generalist_control.reports.figures import draw_figures
from generalist_control.reports.gates import gate_weights, policy_of_run
from generalist_control.reports.report_settings import ReportJob, ReportSettings, Tolerance
from generalist_control.reports.runs import (
    NO_RUN,
    SWEEP_COMMANDS,
    ByConfig,
    RunPoint,
    Sweeps,
    infer_recipe,
    point_label,
    run_label,
    unique_points,
)
from generalist_control.reports.selection import select_runs
from generalist_control.tracking import mlflow_utils

__all__ = ["OWNED", "Inputs", "build_report", "runs_table", "write_report"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Inputs:
    """What the tables read besides the drawn runs: every seed, evaluations, recipe, rules."""

    tolerance: Tolerance
    bar: Mapping[str, Any]
    by_config: ByConfig | None = None  #: None: the drawn runs
    evaluations: Mapping[str, evals.Evaluation] = field(default_factory=dict)  #: by run id
    recipe: str | None = None  #: None: read from the runs' params


def runs_table(sweeps: Sweeps) -> pd.DataFrame:
    """One row per sweep point: its run (or "no run") and the run's figures."""
    rows = []
    for sweep, by_value in sweeps.items():
        for value, p in by_value.items():
            figures = (
                (p.run_id, p.run_name, p.hidden, p.experts, p.seed, p.n_parameters,
                 p.train_loss, p.val_loss, p.diverged) if p else (None,) * 9
            )  # fmt: skip
            rows.append((sweep, value, point_label(sweep, value), "ok" if p else NO_RUN, *figures))
    cols = ["sweep", "value", "label", "status", "run_id", "run_name", "hidden", "experts",
            "seed", "n_parameters", "final_train_loss", "final_val_loss",
            "closed_loop_diverged"]  # fmt: skip
    return pd.DataFrame(rows, columns=cols)


#: The names a report writes (the only entries of ``report.out_dir`` it may replace).
OWNED: dict[str, str | None] = dict.fromkeys(
    [
        *(f"{kind}_{sweep}.{ext}" for kind in ("mse", "loss") for sweep in ("hidden", "experts")
          for ext in ("csv", "png")),
        *(f"{name}.{ext}" for name in ("params_vs_mse", "gate_weights") for ext in ("csv", "png")),
        "fig_hidden_ablation.png", "fig_expert_ablation.png",
        "runs.csv", "points.csv", "claims.csv", "scenarios.csv", "comparison.md", "summary.json",
    ]
)  # fmt: skip


def report_tables(
    sweeps: Sweeps, plants: Sequence[str], gates: pd.DataFrame | None, inputs: Inputs
) -> dict[str, Any]:
    """Every table the report writes, from the drawn runs, every seed and the evaluations."""
    by_config = inputs.by_config or {(p.hidden, p.experts): [p] for p in unique_points(sweeps)}
    runs = [p for group in by_config.values() for p in group]
    recipe = inputs.recipe or infer_recipe(runs)
    labels = {p.run_id: run_label(p) for p in sorted(runs, key=lambda p: (p.hidden, p.experts))}
    worst = evals.scenario_worst(labels, inputs.evaluations)
    return {
        "runs": runs_table(sweeps),
        "points": evals.points_frame(by_config, plants, inputs.evaluations),
        "claims": judge_claims(by_config, gates, inputs.tolerance, recipe),
        "scenarios": evals.scenario_scores(labels, inputs.evaluations),
        "worst": worst,
        "separating": evals.separating(worst, inputs.bar),
        "recipe": recipe,
        "labels": labels,
    }


def _summary(
    sweeps: Sweeps, gate_run: RunPoint | None, plants: Sequence[str], tables: Mapping[str, Any]
) -> dict[str, Any]:
    """``summary.json``: the run of each point, the missing ones, the claims, the recipe."""
    by_label = {p.label: p for p in unique_points(sweeps)}
    points = tables["points"].drop_duplicates("run_id").set_index("run_id")
    return {
        "points": {
            sweep: {point_label(sweep, v): (p.run_id if p else None) for v, p in by_v.items()}
            for sweep, by_v in sweeps.items()
        },
        "missing": [
            point_label(s, v) for s, by_v in sweeps.items() for v, p in by_v.items() if p is None
        ],  # fmt: skip
        "gate_run": gate_run.run_id if gate_run else None,
        "plants": list(plants),
        "configs": {
            label: {
                "run_id": p.run_id,
                "final_train_loss": finite(p.train_loss),
                "n_parameters": finite(p.n_parameters),
                "mse_mean": finite(points.loc[p.run_id, "mse_mean"]),
            }
            for label, p in by_label.items()
        },  # fmt: skip
        "recipe": tables["recipe"],
        "claims": tables["claims"].to_dict(orient="records"),
        "claims_verdicts": verdict_counts(tables["claims"]),
        "separating_scenarios": dict(tables["separating"]),
        "runs": {r: str(i) for i, r in tables["labels"].items()},
    }


def write_report(
    out_dir: str | Path,
    sweeps: Sweeps,
    plants: Sequence[str],
    inputs: Inputs,
    gate: tuple[RunPoint, pd.DataFrame] | None = None,
) -> dict[str, Any]:
    """Write every table, draw the figures from them, publish ``out_dir``; the summary.

    ``out_dir`` is replaced only if it holds nothing but a report's own outputs; ``sweeps``
    from :func:`~generalist_control.reports.runs.select_sweeps`; ``plants`` those of the MSE
    figures; ``gate``: the gate-weight model's run and its gates (no gate figure without it).
    """
    check_replaceable(out_dir, OWNED, "report.out_dir")
    sweeps = {k: dict(v) for k, v in sweeps.items()}
    gate_run, gates = gate if gate is not None else (None, None)
    tables = report_tables(sweeps, plants, gates, inputs)
    with staging_directory(out_dir) as staging:
        for name in ("runs", "points", "claims", "scenarios"):
            tables[name].to_csv(staging / f"{name}.csv", index=False)
        if gates is not None:
            gates.to_csv(staging / "gate_weights.csv")
        draw_figures(staging, staging)
        text = comparison_markdown(tables, gates, gate_run, tables["recipe"])
        (staging / "comparison.md").write_text(text)
        summary = _summary(sweeps, gate_run, plants, tables)
        write_json(staging / "summary.json", summary)
        publish_directory(staging, out_dir, OWNED, "report.out_dir")
    return summary


def _report_metrics(summary: Mapping[str, Any]) -> dict[str, float]:
    """``report/missing_points``, ``ablation/<figure>/d32_M3``, ``claims/<verdict>``."""
    metrics = {"report/missing_points": float(len(summary["missing"]))}
    for label, fig in summary["configs"].items():
        key = label.replace("=", "").replace(",", "_")  # d32_M3
        for name in ("final_train_loss", "n_parameters", "mse_mean"):
            value = fig.get(name)
            if value is not None and np.isfinite(value):
                metrics[f"ablation/{name}/{key}"] = float(value)
    for verdict, count in (summary.get("claims_verdicts") or {}).items():
        metrics[f"claims/{verdict.replace(' ', '_')}"] = float(count)
    return metrics


def _log_report(job: ReportJob, experiment: str, summary: Mapping[str, Any]) -> str:
    """Log the report as a run of kind ``report`` (left out of the run search); its run id."""
    settings = job.report
    exp_id = mlflow_utils.experiment_id(job.logger, kind="report")
    with mlflow.start_run(experiment_id=exp_id, run_name=redact(settings.run_name)) as active:
        mlflow.set_tags(
            {
                RUN_TYPE_TAG: "report",
                "report.kind": "ablation",
                "report.recipe": str(summary.get("recipe")),
                "report.missing": ", ".join(summary["missing"]) or "none",
                "report.source_experiment": experiment,
                "report.mixed_params": json.dumps(summary.get("mixed") or {})[:5000],
            }
        )
        params = {"report": dataclasses.asdict(settings)}
        mlflow.log_params(mlflow_utils.flatten_params(params))
        mlflow.log_dict(dict(summary), "ablation/summary.json")
        mlflow.log_artifacts(settings.out_dir, "ablation")
        mlflow.log_metrics(_report_metrics(summary))
        return active.info.run_id


def _gate_model(
    sweeps: Sweeps, settings: ReportSettings, client: Any
) -> tuple[RunPoint, pd.DataFrame] | None:
    """The run of the gate-weight model (``M = gate.experts`` at the baseline d) and its gates."""
    config = (settings.baseline.hidden, settings.gate.experts)
    run = next((p for p in unique_points(sweeps) if (p.hidden, p.experts) == config), None)
    if run is None:
        return None
    policy, meta = policy_of_run(run.run_id, client)
    return run, gate_weights(policy, meta, settings.gate.plants, settings.gate.duration)


def build_report(job: ReportJob) -> dict[str, Any]:
    """Find the sweep runs, write ``report.out_dir`` and log the report to MLflow.

    Raises
    ------
    NoAblationRunsError
        If the experiment holds no finished training run at all; nothing is written.
    MixedRunsError
        If the runs differ in more than the swept keys and ``report.allow_mixed`` is false
        (:func:`~generalist_control.reports.selection.check_comparable`); nothing is written.
    """
    torch.set_num_threads(job.threads)
    settings = job.report
    client = mlflow.MlflowClient(mlflow_utils.set_tracking(job.logger))
    experiment, sweeps, mixed, by_config = select_runs(settings, job.logger, client)
    plants = list(job.plants) or sorted({k for p in unique_points(sweeps) for k in p.mse})
    runs = [p for group in by_config.values() for p in group]
    evaluations = evals.match(evals.load_evaluations(settings.evaluations_dir), runs)
    if settings.evaluations_dir and not evaluations:
        log.warning("no evaluation under %s: the report has no verdicts", settings.evaluations_dir)
    inputs = Inputs(settings.claims, job.bar, by_config, evaluations, settings.recipe)
    gate = _gate_model(sweeps, settings, client)
    summary = write_report(settings.out_dir, sweeps, plants, inputs, gate)
    if summary["missing"]:
        log.warning("no run for %s; create them with: %s", ", ".join(summary["missing"]),
                    " and ".join(SWEEP_COMMANDS))  # fmt: skip
    if mixed:
        summary["mixed"] = mixed
    if settings.log_mlflow:
        summary["report_run_id"] = _log_report(job, experiment, summary)
    log.info("ablation report written to %s", settings.out_dir)
    return summary
