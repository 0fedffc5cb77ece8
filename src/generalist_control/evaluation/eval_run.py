"""The evaluation's record: where it came from, and its MLflow run.

What reproduces goes into ``summary.json``; the date, the machine and MLflow's ids into the
git-ignored ``provenance.json``. The run is nested under the policy's training run (its
figures linked to the logged model), else in the ``evaluate`` experiment.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import mlflow
import torch
from mlflow.exceptions import MlflowException

from generalist_control.common.atomic import MARKER
from generalist_control.common.secrets import redact
from generalist_control.tracking import mlflow_utils

__all__ = [
    "EvalRun",
    "command",
    "evaluation_run",
    "flat_metrics",
    "machine",
    "provenance",
    "weights_digest",
]


def weights_digest(policy: torch.nn.Module, config: Any) -> str:
    """SHA-256 of a network's config and weights (unlike the file's, blind to its run)."""
    digest = hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode())
    for name, tensor in sorted(policy.state_dict().items()):
        t = tensor.detach().cpu().contiguous()
        digest.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        digest.update(t.flatten().view(torch.uint8).numpy().tobytes())
    return f"sha256:{digest.hexdigest()}"


def machine() -> str:
    """The machine in a few words: processor, cores, system, Python."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:  # Linux: the model name, as lscpu prints it
            names = [line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return (
        f"{cpu}, {os.cpu_count()} cores, {platform.system()}, Python {platform.python_version()}"
    )


def command(argv: list[str] | None = None) -> str:
    """The command line as typed: ``python -m generalist_control.<stage> ...`` for a stage.

    Examples
    --------
    >>> command(["/x/src/generalist_control/evaluate.py", "experiment=tag_free"])
    'python -m generalist_control.evaluate experiment=tag_free'
    """
    argv = list(sys.argv if argv is None else argv)
    path = Path(argv[0])
    head = f"python {path.name}"
    if path.parent.name == "generalist_control":
        head = f"python -m generalist_control.{path.stem}"
    return " ".join([head, *argv[1:]])


def provenance() -> dict[str, str]:
    """The date (UTC), this machine (:func:`machine`) and the command (credentials masked)."""
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        "machine": machine(),
        "command": redact(command()),
    }


#: The tag that says what kind of work a run holds (a report's is ``report``).
RUN_TYPE_TAG = "gc.run_type"


def flat_metrics(summary: Mapping[str, Any], prefix: str) -> dict[str, float]:
    """The summary's figures as MLflow metrics ``<prefix>/...`` (a verdict: 1 met, 0 not)."""
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
    return flat


@dataclass(frozen=True)
class EvalRun:
    """An open evaluation run: its id, the training run and model it evaluates, its prefix."""

    run_id: str
    source_run_id: str | None
    model_id: str | None
    prefix: str

    def log(self, summary: Mapping[str, Any], folder: Path) -> None:
        """Log the summary's figures and every file in ``folder`` (the outputs as written)."""
        mlflow.log_metrics(flat_metrics(summary, self.prefix), model_id=self.model_id)
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            rel = path.relative_to(folder)
            if not rel.name.startswith(MARKER):
                mlflow.log_artifact(str(path), "/".join([self.prefix, *rel.parent.parts]))

    def record(self) -> dict[str, Any]:
        """Where the run is, for ``provenance.json``."""
        return {"run_id": self.run_id, "tracking_uri": redact(mlflow.get_tracking_uri())}


def _training_run(run_id: str | None) -> Any:
    """The training run ``run_id`` if this store holds it, else None."""
    if not run_id:
        return None
    try:
        return mlflow.MlflowClient().get_run(run_id)
    except MlflowException:
        return None  # the policy comes from another store


@contextmanager
def evaluation_run(
    logger: Mapping[str, Any], prefix: str, source_run_id: str | None, tags: Mapping[str, str]
) -> Iterator[EvalRun]:
    """An evaluation run (module docstring): FINISHED, FAILED on an error, KILLED by a signal.

    ``logger``: the ``logger`` config; ``source_run_id``: the policy's training run.
    """
    training = _training_run(source_run_id)
    nest: dict[str, str] = {}
    if training is not None and source_run_id:
        exp_id = training.info.experiment_id
        mlflow_utils.tag_kind(mlflow.MlflowClient().get_experiment(exp_id))
        outputs = training.outputs.model_outputs if training.outputs else []
        model_id = outputs[-1].model_id if outputs else None
        name, nest = f"{prefix} {training.info.run_name}", {"mlflow.parentRunId": source_run_id}
    else:
        exp_id = mlflow_utils.experiment_id(logger, kind="evaluate")
        model_id, name = None, prefix
    mlflow_utils.end_stale_runs(exp_id)
    own = {RUN_TYPE_TAG: "evaluation", "gc.source_run_id": source_run_id or "", **tags}
    tags = {**nest, **mlflow_utils.process_tags(), **own}
    run = mlflow.start_run(experiment_id=exp_id, run_name=redact(name), tags=tags)
    source = source_run_id if training is not None else None
    try:
        yield EvalRun(run.info.run_id, source, model_id, prefix)
    except BaseException as exc:
        mlflow.end_run("FAILED" if isinstance(exc, Exception) else "KILLED")
        raise
    mlflow.end_run("FINISHED")
