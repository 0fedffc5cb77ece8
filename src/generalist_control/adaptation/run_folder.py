"""What an adaptation leaves: its run folder, its MLflow run and a registered model version.

``run_dir`` holds ``policy.ckpt``, ``adapt.json`` and ``plants/<name>.yaml``; it is staged and
swapped in last, after the version is registered: a complete-looking folder has its version.
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

from generalist_control.adaptation.job import AdaptJob
from generalist_control.common.atomic import (
    publish_directory,
    staging_directory,
)
from generalist_control.common.jsonsafe import write_json
from generalist_control.common.secrets import redact
from generalist_control.model.policy import POLICY_FILE, Policy, policy_sha256, save_policy
from generalist_control.tracking import mlflow_utils
from generalist_control.tracking.mlflow_utils import POLICY_HASH_TAG, find_training_run
from generalist_control.training.outputs import log_model

__all__ = [
    "ADAPT_FILE",
    "base_version",
    "end_message",
    "publish",
]

#: The adaptation's record beside its policy.
ADAPT_FILE = "adapt.json"
#: The setting a run folder's marker names: ``run_dir`` of ``adapt``.
SETTING = "run_dir"


def base_version(source: str, run_id: str | None, name: str | None) -> str | None:
    """The registered version the base policy is: from a ``models:/`` URI, else its run's."""
    if not name:
        return None
    if source.startswith("models:/"):
        model, _, version = source[len("models:/") :].partition("/")
        return version or None if model == name else None
    if not run_id:
        return None
    try:
        versions = mlflow.MlflowClient().search_model_versions(f"run_id='{run_id}'")
    except MlflowException:
        return None
    found = sorted((int(v.version) for v in versions if v.name == name), reverse=True)
    return str(found[0]) if found else None


def _log(
    job: AdaptJob, record: Mapping[str, Any], policy: Policy, base: str | None, base_run: str
) -> None:
    """The run's params, tags and metrics."""
    settings = {f"adapt.{k}": str(v) for k, v in dataclasses.asdict(job.request.adapt).items()}
    mlflow.log_params({
        "plant": job.new.name, "plant.file": str(job.new.path),
        "policy": redact(job.request.policy), "demos": str(job.demos["source"]),
        "tag": str(job.new.plant.tag), "n_tags": str(policy.net.n_tags),
        "init.chosen": str(record["init"]["chosen"]), **settings,
    })  # fmt: skip
    mlflow.set_tags({
        "adapt.plant": job.new.name, "adapt.base_run_id": base_run,
        "adapt.base_version": str(base), "run_dir": str(job.request.run_dir),
        "data.content_hash": str(job.demos.get("content_hash") or job.demos["source"]),
    })  # fmt: skip
    for i, loss in enumerate(record.get("loss", [])):
        mlflow.log_metric("adapt/loss", loss, step=i)
    scores = record["closed_loop"]
    for i, score in enumerate(scores.get("rounds", [])):
        mlflow.log_metric("adapt/closed_loop/round", score, step=i + 1)
    flat = {f"adapt/closed_loop/{k}": scores[k] for k in ("start", "fit") if k in scores}
    flat.update({
        "adapt/closed_loop": scores["kept"], "adapt/wall_s": record["wall_s"],
        "adapt/windows": record["demonstrations"]["windows"],
        "adapt/dagger_windows": record["demonstrations"].get("dagger_windows", 0),
    })  # fmt: skip
    if "recorded_relative_mse" in record:
        flat["adapt/recorded_relative_mse"] = record["recorded_relative_mse"]
    mlflow.log_metrics({k: float(v) for k, v in flat.items()})


def _write(folder: Path, job: AdaptJob, policy: Policy, meta: dict, record: dict) -> list[Path]:
    """The policy, its record and the plant's file, written into ``folder``."""
    (folder / "plants").mkdir()
    plant_file = folder / "plants" / f"{job.new.name}.yaml"
    shutil.copyfile(job.new.path, plant_file)
    return [save_policy(folder / POLICY_FILE, policy, meta),
            write_json(folder / ADAPT_FILE, record), plant_file]  # fmt: skip


def publish(
    job: AdaptJob, policy: Policy, meta: dict[str, Any], record: dict[str, Any]
) -> dict[str, Any]:
    """Log the run, register the model, then put the run folder in place (last).

    Interrupted, the run ends KILLED and no run folder appears; any other error: FAILED.
    """
    logger = dict(job.request.logger)
    logger["run_name"] = redact(logger["run_name"]) or f"adapt-{job.new.name}"
    name = logger["registered_model_name"]
    run_dir = job.request.run_dir
    with (
        staging_directory(run_dir) as staging,
        mlflow_utils.mlflow_run(logger, kind="adapt") as run,
    ):
        try:
            base_run = find_training_run(job.base_sha256) or ""
            record["base_version"] = base = base_version(job.request.policy, base_run, name)
            written = _write(staging, job, policy, meta, record)
            mlflow.set_tag(POLICY_HASH_TAG, policy_sha256(written[0]))  # found as a training's
            for path in written:
                mlflow.log_artifact(
                    str(path), path.parent.name if path.suffix == ".yaml" else "policy"
                )
            _log(job, record, policy, base, base_run)
            version = None
            if logger["log_model"]:  # the MLflow model, its version tagged with base and plant
                keys = ("state", "mask", "ref", "tag")
                windows = {k: torch.from_numpy(getattr(job.windows, k)[:8]) for k in keys}
                tags = {
                    "base_version": base or "",
                    "base_run_id": base_run,
                    "adapted_plant": job.new.name,
                    "adapted_tag": str(job.new.plant.tag),
                }
                version = log_model(policy, windows, name, tags)
            publish_directory(staging, run_dir, {}, SETTING)
        except KeyboardInterrupt:
            mlflow.end_run("KILLED")
            raise
    experiment = mlflow.MlflowClient().get_experiment(run.info.experiment_id).name
    return {
        "policy_path": run_dir / POLICY_FILE, "run_id": run.info.run_id,
        "experiment": experiment, "registered_version": version, "base_version": base,
    }  # fmt: skip


def evaluate_command(job: AdaptJob, policy_path: Path) -> str:
    """The command that evaluates the adapted policy on the plant, every scenario."""
    name, run_dir = job.new.name, job.request.run_dir
    words = ["python -m generalist_control.evaluate"]
    if not job.new.in_catalogue:  # the run folder's plants/ holds the plant's file
        words.append(f"'hydra.searchpath=[file://{run_dir.resolve()}]'")
    if name not in job.request.listed:
        words.append(f"+plants@systems.plants.{name}={name}")
    words += [f"systems.include=[{name}]", f"policy={policy_path}",
              f"paths.reports_dir={run_dir / 'eval'}"]  # fmt: skip
    return " ".join(words)


def end_message(job: AdaptJob, objects: Mapping[str, Any]) -> str:
    """The lines an adaptation ends with: the policy, the run, the model, how to evaluate."""
    uri = redact(mlflow.get_tracking_uri())
    version, base = objects["registered_version"], objects["base_version"]
    model = job.request.logger["registered_model_name"]
    registered = (
        f"registered model {model} version {version} (adapted from version {base or '-'})"
        if version
        else "not registered"
    )
    return (
        f"plant '{job.new.name}' added on tag {job.new.plant.tag}; MLflow run "
        f"{objects['run_id']} in experiment '{objects['experiment']}' ({uri}); {registered}\n"
        f"evaluate it with: {evaluate_command(job, objects['policy_path'])}\n"
        f"policy written to {objects['policy_path']}"
    )
