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
    cfg: Any, meta: Mapping[str, Any], summary: Mapping[str, Any], out_dir: Path
) -> str | None:
    """Log the summary figures and the report folder to the evaluated model's MLflow run."""
    flat: dict[str, float] = {}
    for scen, vals in summary.get("ratios", {}).items():
        for k, v in vals.items():
            if isinstance(v, (int, float)) and math.isfinite(v):
                flat[f"eval/{scen}/{k}"] = float(v)
    for ctrl, by_scen in summary.get("diverged", {}).items():
        flat[f"eval/diverged/{ctrl}"] = float(sum(by_scen.values()))
    with mlflow_run(cfg.logger, resume_run_id=meta.get("mlflow_run_id")) as run:
        mlflow.log_metrics(flat)
        mlflow.log_artifacts(str(out_dir), "eval")
        return run.info.run_id
