"""The evaluation's figures and report folder, logged to the evaluated model's MLflow run."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import mlflow

from generalist_control.tracking.mlflow_utils import mlflow_run

__all__ = ["log_to_mlflow"]


def log_to_mlflow(
    cfg: Any,
    meta: Mapping[str, Any],
    summary: Mapping[str, Any],
    out_dir: Path,
) -> str | None:
    """Log the summary figures and the report folder to the evaluated model's MLflow run.

    Names start with ``evaluation.mlflow_prefix`` (default ``eval``), so that two
    evaluations of one policy (e.g. on other scenarios) keep apart in its run. The
    quality-bar verdicts are metrics too, ``<prefix>/bar/<verdict>`` 1 (met) or 0 (a verdict
    not measured is left out), with ``<prefix>/bar_passed`` and ``<prefix>/bar_checked``, so
    that MLflow's Compare view shows them beside the scores.
    """
    prefix = str(cfg.evaluation.get("mlflow_prefix") or "eval")
    flat: dict[str, float] = {}
    for scen, vals in summary.get("ratios", {}).items():
        for k, v in vals.items():
            if isinstance(v, (int, float)) and math.isfinite(v):
                flat[f"{prefix}/{scen}/{k}"] = float(v)
    for ctrl, by_scen in summary.get("diverged", {}).items():
        flat[f"{prefix}/diverged/{ctrl}"] = float(sum(by_scen.values()))
    verdicts = {k: v for k, v in (summary.get("quality_bar") or {}).items() if v is not None}
    for name, met in verdicts.items():
        flat[f"{prefix}/bar/{name}"] = 1.0 if met else 0.0
    if verdicts:
        flat[f"{prefix}/bar_passed"] = float(sum(bool(v) for v in verdicts.values()))
        flat[f"{prefix}/bar_checked"] = float(len(verdicts))
    setpoint = summary.get("setpoint") or {}
    if setpoint:
        flat[f"{prefix}/setpoint/unsettled"] = float(len(setpoint["unsettled"]))
        for k in ("worst_radius_GC", "worst_tail_error_GC"):
            if math.isfinite(setpoint[k]):
                flat[f"{prefix}/setpoint/{k}"] = float(setpoint[k])
    with mlflow_run(cfg.logger, resume_run_id=meta.get("mlflow_run_id")) as run:
        mlflow.log_metrics(flat)
        mlflow.log_artifacts(str(out_dir), prefix)
        return run.info.run_id
