"""The ``evaluate`` stage: ``python -m generalist_control.evaluate`` or ``dvc repro evaluate``.

Every scenario of ``conf/evaluation`` runs the trained policy (GC), the LQI expert and LQI
with anti-windup on each plant, in one loop with the set-point check's long holds
(:func:`generalist_control.evaluation.runner.run_suite`).
Outputs under ``paths.reports_dir`` (default ``reports/eval``): ``metrics.csv`` in long form
(system, scenario, controller, run, metric, value), ``summary.json`` (the quality-bar
figures, DVC metrics), ``setpoint.csv`` (each plant's loop linearised at rest and a long
hold's tail, ``evaluation.setpoint``; :mod:`generalist_control.evaluation.setpoint`),
``table2.md`` (the paper's Table 2 layout with the paper's values
beside ours), ``table_all.md`` (the same for every plant), ``responses.csv`` (DVC plots)
and PNG plots; all are logged to the MLflow run of the evaluated model.

Where the time goes and what runs beside what (docs/evaluation.md, "Run time"): MLflow is
imported and its store opened in a process of its own
(:mod:`~generalist_control.evaluation.tracker`), and the figures are drawn by another that
makes ready from the start (:mod:`~generalist_control.evaluation.background`), both while
this one works.
"""

from __future__ import annotations

import sys

from generalist_control.evaluation.tracker import MlflowWorker, start_early

#: Hydra's flags that only print (the stage does not run, so MLflow is not needed).
_PRINT_ONLY = {"--help", "-h", "--hydra-help", "--cfg", "-c", "--info", "-i",
               "--shell-completion", "-sc"}  # fmt: skip

if __name__ == "__main__" and not _PRINT_ONLY & set(sys.argv[1:]):
    start_early()  # the MLflow worker imports MLflow while this process imports the rest

import gc
import json
import logging
import os
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig
from threadpoolctl import threadpool_limits

from generalist_control.common.configs import as_dict
from generalist_control.common.paths import HYDRA_CONFIG_PATH
from generalist_control.deploy.policy_source import resolve
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation import background
from generalist_control.evaluation.provenance import policy_record, provenance
from generalist_control.evaluation.runner import run_suite
from generalist_control.evaluation.setpoint import setpoint_settings
from generalist_control.evaluation.variants import check_variants_dir, run_variants
from generalist_control.evaluation.writer import check_reports_dir, write_reports
from generalist_control.model.policy import POLICY_FILE, load_policy
from generalist_control.plants.catalog import plants_from_config
from generalist_control.plants.plant import Plant

__all__ = ["main", "run"]

log = logging.getLogger(__name__)


def _runtime(cfg: DictConfig, tracker: MlflowWorker) -> tuple[PolicyRuntime, dict[str, Any]]:
    """The policy's runtime and its record (:mod:`~generalist_control.evaluation.provenance`)."""
    source = cfg.get("policy") or str(Path(cfg.paths.models_dir) / POLICY_FILE)
    if not Path(str(source)).is_file():  # a runs:/ or models:/ URI: MLflow fetches it here
        import mlflow

        mlflow.set_tracking_uri(tracker.ready())
    path = resolve(source)
    policy, meta = load_policy(path)
    runtime = PolicyRuntime(policy, meta, backend=cfg.evaluation.get("backend", "torch"))
    return runtime, {"policy": policy_record(source, path, meta), "provenance": provenance()}


def _evaluate(
    cfg: DictConfig,
    runtime: PolicyRuntime,
    plants: list[Plant],
    record: dict[str, Any],
    tracker: MlflowWorker,
) -> dict[str, Any]:
    """Every scenario, the Crazyflie, the set-point check, the reports written; the summary."""
    scen = as_dict(cfg.evaluation.scenarios)
    cf = as_dict(cfg.evaluation.get("crazyflie") or {})
    spec = as_dict(cfg.evaluation.get("setpoint") or {})
    bar = as_dict(cfg.evaluation.get("quality_bar") or {})
    # the figures are drawn in processes of their own while the reports are written
    with background.figures_beside(bool(cfg.evaluation.get("plots", True))) as figures:
        ev = run_suite(runtime, plants, scen, cf, setpoint=setpoint_settings(spec, runtime))
        if figures is not None:
            figures.draw(ev.trajectories)
        tracker.ready()  # a store that cannot be opened stops us before any output changes
        return write_reports(ev.metrics, ev.trajectories, Path(cfg.paths.reports_dir),
                             figures or False, bar, ev.setpoint, record)  # fmt: skip


def run(cfg: DictConfig) -> dict[str, Any]:
    """Load the policy, evaluate it on ``cfg.systems`` and write (and log) the reports."""
    out_dir = Path(cfg.paths.reports_dir)
    variants = bool((cfg.evaluation.get("variants") or {}).get("enabled", False))
    # refuse a folder of someone else's files before any work
    (check_variants_dir if variants else check_reports_dir)(out_dir)
    prefix = str(cfg.evaluation.get("mlflow_prefix") or "eval")
    # MLflow imports and opens its store in a process of its own while we work. BLAS on one
    # thread: the matrices here are at most 5 x 5, and OpenBLAS's threads only wait on each
    # other (its triangular solves ten times slower on a busy machine); the same numbers.
    with MlflowWorker(as_dict(cfg.logger), prefix) as tracker, threadpool_limits(1, "blas"):
        runtime, record = _runtime(cfg, tracker)
        plants = plants_from_config(cfg.systems)
        if variants:  # unseen plant variants instead (evaluation.variants, experiment=variants)
            tracker.ready()
            summary = run_variants(cfg, runtime, plants, record)
        else:
            summary = _evaluate(cfg, runtime, plants, record, tracker)
        tracker.log(runtime.meta.get("mlflow_run_id"), summary, out_dir)
    if variants:
        log.info("variants evaluation written to %s: pass=%s", out_dir, summary["pass"])
    else:
        log.info("evaluation written to %s: %s", out_dir, json.dumps(summary["quality_bar"]))
    return summary


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``evaluate`` stage."""
    run(cfg)


if __name__ == "__main__":
    # what the imports built lives to the end: no collection walks it again (nor at exit)
    gc.freeze()
    if not _PRINT_ONLY & set(sys.argv[1:]):
        background.start_early()  # the figures' process makes ready while Hydra composes
    main()
    # everything is written, logged and closed: skip the interpreter's teardown of torch,
    # ONNX Runtime and pandas (0.2 s); a failed run leaves by SystemExit above, as before
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
