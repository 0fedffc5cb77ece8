"""The ``evaluate`` stage: ``python -m generalist_control.evaluate`` or ``dvc repro evaluate``.

Every scenario of ``conf/evaluation`` runs the trained policy (GC), the LQI expert and LQI
with anti-windup on each plant (:func:`generalist_control.evaluation.runner.evaluate`).
Outputs under ``paths.reports_dir`` (default ``reports/eval``): ``metrics.csv`` in long form
(system, scenario, controller, run, metric, value), ``summary.json`` (the quality-bar
figures, DVC metrics), ``setpoint.csv`` (each plant's loop linearised at rest and a long
hold's tail, ``evaluation.setpoint``; :mod:`generalist_control.evaluation.setpoint`),
``table2.md`` (the paper's Table 2 layout with the paper's values
beside ours), ``table_all.md`` (the same for every plant), ``responses.csv`` (DVC plots)
and PNG plots; all are logged to the MLflow run of the evaluated model.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from generalist_control.common.configs import as_dict
from generalist_control.common.paths import HYDRA_CONFIG_PATH
from generalist_control.deploy.resolve import resolve
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.mlflow_log import log_to_mlflow
from generalist_control.evaluation.provenance import policy_record, provenance
from generalist_control.evaluation.runner import evaluate
from generalist_control.evaluation.setpoint import setpoint_from_config
from generalist_control.evaluation.variants import check_variants_dir, run_variants
from generalist_control.evaluation.writer import check_reports_dir, write_reports
from generalist_control.model.policy import POLICY_FILE, load_policy
from generalist_control.plants.catalog import plants_from_config
from generalist_control.tracking import mlflow_utils

__all__ = ["main", "run"]

log = logging.getLogger(__name__)


def run(cfg: DictConfig) -> dict[str, Any]:
    """Load the policy, evaluate it on ``cfg.systems`` and write (and log) the reports."""
    out_dir = Path(cfg.paths.reports_dir)
    variants = bool((cfg.evaluation.get("variants") or {}).get("enabled", False))
    # refuse a folder of someone else's files before any work
    (check_variants_dir if variants else check_reports_dir)(out_dir)
    source = cfg.get("policy") or str(Path(cfg.paths.models_dir) / POLICY_FILE)
    mlflow_utils.set_tracking(cfg.logger)  # for runs:/ and models:/ policy URIs
    path = resolve(source)
    policy, meta = load_policy(path)
    runtime = PolicyRuntime(policy, meta, backend=cfg.evaluation.get("backend", "torch"))
    record = {"policy": policy_record(source, path, meta), "provenance": provenance()}
    plants = plants_from_config(cfg.systems)
    if variants:  # unseen plant variants instead (evaluation.variants, experiment=variants)
        summary = run_variants(cfg, runtime, plants, record)
        log_to_mlflow(cfg, runtime.meta, summary, out_dir)
        log.info("variants evaluation written to %s: pass=%s", out_dir, summary["pass"])
        return summary
    scen = as_dict(cfg.evaluation.scenarios)
    cf = as_dict(cfg.evaluation.get("crazyflie") or {})
    df, trajs = evaluate(runtime, plants, scen, cf)
    plots = bool(cfg.evaluation.get("plots", True))
    bar = as_dict(cfg.evaluation.get("quality_bar") or {})
    setpoint = setpoint_from_config(as_dict(cfg.evaluation.get("setpoint") or {}), runtime, plants)
    summary = write_reports(df, trajs, out_dir, plots, bar, setpoint, record)
    log_to_mlflow(cfg, runtime.meta, summary, out_dir)
    log.info("evaluation written to %s: %s", out_dir, json.dumps(summary["quality_bar"]))
    return summary


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``evaluate`` stage."""
    run(cfg)


if __name__ == "__main__":
    main()
