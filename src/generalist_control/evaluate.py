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

import hashlib
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import hydra
import pandas as pd
from omegaconf import DictConfig

from generalist_control.common.configs import as_dict
from generalist_control.common.paths import HYDRA_CONFIG_PATH
from generalist_control.common.secrets import redact
from generalist_control.deploy.resolve import resolve
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.handover import handover_table
from generalist_control.evaluation.identity import identity_trace
from generalist_control.evaluation.local_gains import local_gains
from generalist_control.evaluation.mlflow_log import log_to_mlflow
from generalist_control.evaluation.runner import evaluate
from generalist_control.evaluation.setpoint import setpoint_from_config
from generalist_control.evaluation.tag_free import check_tag_free_dir, write_tag_free_report
from generalist_control.evaluation.variants import check_variants_dir, run_variants
from generalist_control.evaluation.writer import check_reports_dir, write_reports
from generalist_control.model.policy import POLICY_FILE, load_policy
from generalist_control.plants.catalog import plants_from_config
from generalist_control.plants.plant import Plant
from generalist_control.tracking import mlflow_utils

__all__ = ["main", "policy_record", "run"]

log = logging.getLogger(__name__)


def policy_record(source: str, path: Path, meta: Mapping[str, Any]) -> dict[str, Any]:
    """What ``summary.json`` says of the evaluated policy: where it came from, which file.

    ``source`` as given (``policy`` or the default file; credentials masked), the MLflow
    run that trained it (None if unknown) and the SHA-256 of the file evaluated.
    """
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    run_id = meta.get("mlflow_run_id")
    return {
        "source": redact(str(source)),
        "mlflow_run_id": str(run_id) if run_id else None,
        "sha256": f"sha256:{digest}",
    }


def _runtime(source: str, path: Path, cfg: DictConfig) -> PolicyRuntime:
    """The policy's runtime; with ``evaluation.withhold_tag`` its network never gets the tag.

    With ``evaluation.identity_given`` (a diagnostic) an ``infer_tag`` network gets the
    true plant's embedding row instead of the one its identity head infers.

    Raises
    ------
    ValueError
        If the tag is to be withheld from a policy trained with its tag always given, or
        the identity given to a policy that does not infer it.
    """
    policy, meta = load_policy(path)
    if cfg.evaluation.get("withhold_tag", False):
        if not (policy.config["tag_free"] or policy.config["unknown_tag"]):
            raise ValueError(
                f"evaluation.withhold_tag=true, but the policy {source} was trained with its "
                "tag always given; train it with model.tag_dropout > 0 or model.tag_free=true "
                "(experiment=tag_free)"
            )
        policy.withhold_tag = True
    if cfg.evaluation.get("identity_given", False):
        if not policy.config["infer_tag"]:
            raise ValueError(
                f"evaluation.identity_given=true, but the policy {source} does not infer its "
                "plant (model.infer_tag); it is a diagnostic of experiment=tag_free policies"
            )
        policy.net.identity_given = True
    return PolicyRuntime(policy, meta, backend=cfg.evaluation.get("backend", "torch"))


def _diagnostics(
    cfg: DictConfig, runtime: PolicyRuntime, plants: list[Plant], step: dict[str, Any] | None
) -> dict[str, pd.DataFrame | None]:
    """The tag-free report's hand-over table, local gains and identity trace (None: off)."""
    if step is None:
        return {}
    samples = cfg.evaluation.get("handover_samples")
    handover = (
        handover_table(runtime, plants, step, [int(n) for n in samples]) if samples else None
    )
    after = cfg.evaluation.get("gain_samples")
    gains = local_gains(runtime, plants, step, int(after)) if after is not None else None
    trace = None
    if runtime.policy.net.identity is not None:  # from the start, and after the gains' N
        trace = identity_trace(runtime, plants, step, [0] + ([int(after)] if after else []))
    return {"handover": handover, "gains": gains, "identity_trace": trace}


def run(cfg: DictConfig) -> dict[str, Any]:
    """Load the policy, evaluate it on ``cfg.systems`` and write (and log) the reports."""
    out_dir = Path(cfg.paths.reports_dir)
    variants = bool((cfg.evaluation.get("variants") or {}).get("enabled", False))
    # refuse a folder of someone else's files before any work
    (check_variants_dir if variants else check_reports_dir)(out_dir)
    tag_free_dir = cfg.evaluation.get("tag_free_report")
    if tag_free_dir:
        check_tag_free_dir(tag_free_dir)
    source = cfg.get("policy") or str(Path(cfg.paths.models_dir) / POLICY_FILE)
    mlflow_utils.set_tracking(cfg.logger)  # for runs:/ and models:/ policy URIs
    path = resolve(source)
    runtime = _runtime(source, path, cfg)
    policy = policy_record(source, path, runtime.meta)
    plants = plants_from_config(cfg.systems)
    if variants:  # unseen plant variants instead (evaluation.variants, experiment=variants)
        summary = run_variants(cfg, runtime, plants, policy)
        log_to_mlflow(cfg, runtime.meta, summary, out_dir)
        log.info("variants evaluation written to %s: pass=%s", out_dir, summary["pass"])
        return summary
    scen = as_dict(cfg.evaluation.scenarios)
    cf = as_dict(cfg.evaluation.get("crazyflie") or {})
    df, trajs = evaluate(runtime, plants, scen, cf)
    plots = bool(cfg.evaluation.get("plots", True))
    bar = as_dict(cfg.evaluation.get("quality_bar") or {})
    setpoint = setpoint_from_config(as_dict(cfg.evaluation.get("setpoint") or {}), runtime, plants)
    summary = write_reports(df, trajs, out_dir, plots, bar, setpoint, policy)
    if tag_free_dir:
        diagnostics = _diagnostics(cfg, runtime, plants, scen.get("step"))
        verdict = write_tag_free_report(
            df, runtime.policy, plants, tag_free_dir, trajectories=trajs, **diagnostics
        )
        log.info("tag-free bar written to %s: met=%s", tag_free_dir, verdict["met"])
    extra = {"tag_free_bar": Path(tag_free_dir)} if tag_free_dir else None
    log_to_mlflow(cfg, runtime.meta, summary, out_dir, extra)
    log.info("evaluation written to %s: %s", out_dir, json.dumps(summary["quality_bar"]))
    return summary


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``evaluate`` stage."""
    run(cfg)


if __name__ == "__main__":
    main()
