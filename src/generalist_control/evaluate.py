"""The ``evaluate`` stage: ``python -m generalist_control.evaluate`` or ``dvc repro evaluate``.

What can refuse (the config, the folder, the MLflow store, the policy) refuses before any
output changes; SIGTERM and SIGINT end it non-zero, its run KILLED, nothing published.
"""

from __future__ import annotations

import gc
import json
import logging
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from generalist_control.common.atomic import folder_lock
from generalist_control.common.secrets import redact
from generalist_control.common.sections import as_dict, read_section
from generalist_control.common.stage_main import stage_main
from generalist_control.common.stop_signals import exiting_on_signals
from generalist_control.data.generation import variants_config
from generalist_control.deploy.policy_source import resolve
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.eval_config import EvaluationSettings, read_evaluation
from generalist_control.evaluation.eval_run import (
    command,
    evaluation_run,
    provenance,
    weights_digest,
)
from generalist_control.evaluation.runner import run_suite
from generalist_control.evaluation.variant_eval import OWNED as VARIANTS_OWNED
from generalist_control.evaluation.variant_eval import TrainingDraws, run_variants
from generalist_control.evaluation.writer import OWNED, check_reports_dir, write_reports
from generalist_control.model.policy import POLICY_FILE, load_policy, policy_sha256
from generalist_control.plants.catalog import plants_from_config
from generalist_control.tracking.mlflow_utils import check_store, find_training_run
from generalist_control.training.settings import DaggerSettings

__all__ = ["main", "run"]

log = logging.getLogger(__name__)


def _training_draws(cfg: DictConfig) -> TrainingDraws:
    """The variants the training may have seen: its ``data.variants`` and ``dagger`` sections."""
    data = variants_config({"variants": {**as_dict(cfg.data.variants), "enabled": True}})
    assert data is not None
    seeds, fresh = range(0), 0
    if cfg.dagger is not None:
        dagger = read_section(DaggerSettings, as_dict(cfg.dagger), "dagger")
        drawn = dagger.sampler.variants
        if drawn is not None:
            seeds, fresh = range(drawn.seed, drawn.seed + dagger.rounds), drawn.fresh
    return TrainingDraws(
        Path(cfg.paths.data_dir), data["seed"], data["range"], data["count"], data["max_tries"],
        seeds, fresh,
    )  # fmt: skip


def _policy(
    cfg: DictConfig, settings: EvaluationSettings
) -> tuple[PolicyRuntime, dict[str, Any], dict[str, str]]:
    """The policy's runtime, its record (:data:`~.evaluation.writer.Record`) and run tags."""
    source = str(cfg.policy or Path(cfg.paths.models_dir) / POLICY_FILE)
    path = resolve(source)  # a runs:/ or models:/ URI: MLflow fetches the file
    policy, meta = load_policy(path)
    runtime = PolicyRuntime(policy, meta, backend=settings.backend)
    digest = weights_digest(policy, policy.config)
    where = provenance()
    run_id = find_training_run(policy_sha256(path))  # the file holds no run id
    record = {
        "summary": {
            "policy": {"source": redact(source), "weights_sha256": digest},
            "provenance": {"command": where["command"]},
        },
        "provenance": {**where, "policy": {"source": redact(source), "file": str(path),
                                           "mlflow_run_id": str(run_id) if run_id else None}},
    }  # fmt: skip
    tags = {"gc.policy_source": redact(source), "gc.weights_sha256": digest,
            "gc.machine": where["machine"], "gc.command": redact(command())}  # fmt: skip
    return runtime, record, tags


def run(cfg: DictConfig) -> dict[str, Any]:
    """Load the policy, evaluate it on ``cfg.systems`` and write (and log) the reports."""
    settings = read_evaluation(as_dict(cfg.evaluation))
    out_dir = Path(cfg.paths.reports_dir)
    logger = as_dict(cfg.logger)
    variants = settings.variants.enabled  # unseen plant variants instead (experiment=variants)
    with folder_lock(out_dir, "evaluation"):  # one evaluation at a time writes a folder
        check_reports_dir(out_dir, VARIANTS_OWNED if variants else OWNED)
        check_store(logger)  # an MLflow store that does not answer: refused now
        runtime, record, tags = _policy(cfg, settings)
        plants = plants_from_config(as_dict(cfg.systems))
        training = _training_draws(cfg) if variants else None
        source_run = record["provenance"]["policy"]["mlflow_run_id"]
        tags["gc.reports_dir"] = str(out_dir)
        with evaluation_run(logger, settings.mlflow_prefix, source_run, tags) as ev_run:
            record["provenance"]["mlflow"] = ev_run.record()
            if training is not None:
                summary = run_variants(
                    settings, runtime, plants, training, out_dir, record, ev_run
                )
            else:
                setpoint = settings.setpoint if runtime.integral else None  # the integral's check
                ev = run_suite(runtime, plants, settings.scenarios, settings.crazyflie, setpoint)
                summary = write_reports(ev, out_dir, settings.quality_bar, record, ev_run,
                                        settings.plots)  # fmt: skip
    verdict = summary["pass"] if settings.variants.enabled else summary["quality_bar"]
    log.info("evaluation written to %s: %s", out_dir, json.dumps(verdict))
    return summary


@stage_main("config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``evaluate`` stage."""
    gc.freeze()  # no collection walks what the imports built (docs/notes/evaluation-speed.md)
    with exiting_on_signals("nothing published, the run KILLED"):
        run(cfg)


if __name__ == "__main__":
    main()
