"""What an adaptation leaves: the policy, its record, the plant's file and its MLflow run.

In ``run_dir`` (``outputs/adapt/<time>`` by default): ``policy.ckpt`` (the grown policy, its
meta naming the plant), ``adapt.json`` (the record of :func:`~.adapt.learn`) and
``plants/<name>.yaml`` (the plant's file, so that ``hydra.searchpath`` can find it for an
evaluation). One MLflow run in the experiment ``<prefix>/adapt``
(:mod:`~generalist_control.tracking.experiments`), and a new version of the registered
model, tagged with the version it was adapted from and the plant.
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import mlflow
import torch
from mlflow.exceptions import MlflowException
from omegaconf import DictConfig

from generalist_control.common.configs import as_dict
from generalist_control.common.jsonsafe import write_json
from generalist_control.common.secrets import redact
from generalist_control.model.policy import POLICY_FILE, Policy, save_policy
from generalist_control.tracking import mlflow_utils
from generalist_control.training.adapt_job import AdaptJob
from generalist_control.training.outputs import check_models_dir, log_model

__all__ = ["ADAPT_FILE", "base_version", "check_run_dir", "end_message", "publish"]

#: The adaptation's record beside its policy.
ADAPT_FILE = "adapt.json"


def check_run_dir(run_dir: Path) -> None:
    """Refuse, before any work, a ``run_dir`` whose ``policy.ckpt`` no training wrote."""
    check_models_dir(run_dir)


def base_version(source: str, meta: Mapping[str, Any], name: str | None) -> str | None:
    """The registered version the base policy is: from a ``models:/`` URI, else its run's."""
    if not name:
        return None
    if source.startswith("models:/"):
        model, _, version = source[len("models:/") :].partition("/")
        return version or None if model == name else None
    run_id = meta.get("mlflow_run_id")
    if not run_id:
        return None
    try:
        versions = mlflow.MlflowClient().search_model_versions(f"run_id='{run_id}'")
    except MlflowException:
        return None
    found = sorted((int(v.version) for v in versions if v.name == name), reverse=True)
    return str(found[0]) if found else None


def _params(job: AdaptJob, record: Mapping[str, Any], policy: Policy) -> dict[str, str]:
    settings = {f"adapt.{k}": str(v) for k, v in dataclasses.asdict(job.settings).items()}
    return {
        "plant": job.new.name,
        "plant.file": str(job.new.path),
        "policy": redact(job.source),
        "demos": str(job.demos["source"]),
        "tag": str(job.new.plant.tag),
        "n_tags": str(policy.net.n_tags),
        "init.chosen": str(record["init"]["chosen"]),
        **settings,
    }


def _metrics(record: Mapping[str, Any]) -> None:
    for i, loss in enumerate(record.get("loss", [])):
        mlflow.log_metric("adapt/loss", loss, step=i)
    scores = record["closed_loop"]
    for i, score in enumerate(scores.get("rounds", [])):
        mlflow.log_metric("adapt/closed_loop/round", score, step=i + 1)
    flat = {f"adapt/closed_loop/{k}": scores[k] for k in ("start", "fit") if k in scores}
    flat["adapt/closed_loop"] = scores["kept"]
    flat["adapt/wall_s"] = record["wall_s"]
    flat["adapt/windows"] = record["demonstrations"]["windows"]
    flat["adapt/dagger_windows"] = record["demonstrations"].get("dagger_windows", 0)
    if "recorded_relative_mse" in record:
        flat["adapt/recorded_relative_mse"] = record["recorded_relative_mse"]
    mlflow.log_metrics({k: float(v) for k, v in flat.items()})


def _register(job: AdaptJob, policy: Policy, name: str | None, base: str | None) -> str | None:
    """Log the MLflow model and register it; tag the version with its base and plant."""
    w = job.windows
    windows = {k: torch.from_numpy(getattr(w, k)[:8]) for k in ("state", "mask", "ref", "tag")}
    version = log_model(policy, windows, name)
    if version is not None and name:
        client = mlflow.MlflowClient()
        for key, value in (
            ("base_version", base or ""),
            ("base_run_id", str(job.meta.get("mlflow_run_id") or "")),
            ("adapted_plant", job.new.name),
            ("adapted_tag", str(job.new.plant.tag)),
        ):
            client.set_model_version_tag(name, version, key, value)
    return version


def publish(
    job: AdaptJob, policy: Policy, meta: dict[str, Any], record: dict[str, Any], cfg: DictConfig
) -> dict[str, Any]:
    """Write the policy, its record and the plant's file; log the run; register the model."""
    logger = as_dict(cfg.logger)
    logger["run_name"] = redact(cfg.logger.get("run_name")) or f"adapt-{job.new.name}"
    name = logger.get("registered_model_name")
    base = base_version(job.source, job.meta, name)
    record["base_version"] = base
    job.run_dir.mkdir(parents=True, exist_ok=True)
    with mlflow_utils.mlflow_run(logger, kind="adapt") as run:
        run_id = run.info.run_id
        meta = {**meta, "mlflow_run_id": run_id}
        policy_path = save_policy(job.run_dir / POLICY_FILE, policy, meta)
        plant_file = job.run_dir / "plants" / f"{job.new.name}.yaml"
        plant_file.parent.mkdir(exist_ok=True)
        shutil.copyfile(job.new.path, plant_file)
        record_path = write_json(job.run_dir / ADAPT_FILE, record)
        mlflow.log_params(_params(job, record, policy))
        mlflow.set_tags({
            "adapt.plant": job.new.name, "adapt.base_run_id": str(job.meta.get("mlflow_run_id")),
            "adapt.base_version": str(base), "run_dir": str(job.run_dir),
            "data.content_hash": str(job.demos.get("content_hash", job.demos["source"])),
        })  # fmt: skip
        _metrics(record)
        for path in (policy_path, record_path, plant_file):
            mlflow.log_artifact(str(path), "policy" if path != plant_file else "plants")
        version = _register(job, policy, name, base) if logger.get("log_model", True) else None
    experiment = mlflow.MlflowClient().get_experiment(run.info.experiment_id).name
    return {
        "policy_path": policy_path, "run_id": run_id, "experiment": experiment,
        "registered_version": version, "base_version": base,
    }  # fmt: skip


def evaluate_command(job: AdaptJob, policy_path: Path, systems: Mapping[str, Any]) -> str:
    """The command that evaluates the adapted policy on the plant, every scenario."""
    name = job.new.name
    words = ["python -m generalist_control.evaluate"]
    if not job.new.in_catalogue:  # the run folder's plants/ holds the plant's file
        words.append(f"'hydra.searchpath=[file://{job.run_dir.resolve()}]'")
    if name not in (systems.get("plants") or {}):
        words.append(f"+plants@systems.plants.{name}={name}")
    words += [
        f"systems.include=[{name}]",
        f"policy={policy_path}",
        f"paths.reports_dir={job.run_dir / 'eval'}",
    ]
    return " ".join(words)


def end_message(job: AdaptJob, objects: Mapping[str, Any], cfg: DictConfig) -> str:
    """The lines an adaptation ends with: the policy, the run, the model, how to evaluate."""
    uri = redact(mlflow.get_tracking_uri())
    version, base = objects["registered_version"], objects["base_version"]
    model = cfg.logger.get("registered_model_name")
    registered = (
        f"registered model {model} version {version} (adapted from version {base or '-'})"
        if version
        else "not registered"
    )
    evaluate = evaluate_command(job, objects["policy_path"], as_dict(cfg.systems))
    return (
        f"plant '{job.new.name}' added on tag {job.new.plant.tag}; MLflow run "
        f"{objects['run_id']} in experiment '{objects['experiment']}' ({uri}); {registered}\n"
        f"evaluate it with: {evaluate}\n"
        f"policy written to {objects['policy_path']}"
    )
