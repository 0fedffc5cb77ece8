"""What a training run leaves behind: the policy file, ``metrics.json`` and its MLflow record."""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import torch
from mlflow.data.numpy_dataset import from_numpy
from mlflow.models import infer_signature
from omegaconf import OmegaConf

from generalist_control.common.secrets import redact
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import (
    POLICY_FILE,
    FlatPolicy,
    Policy,
    PolicyFileError,
    flat_columns,
    load_policy,
)
from generalist_control.simulation.comparison import output_mse
from generalist_control.tracking import mlflow_utils, training_run
from generalist_control.training.datamodule import DemoDataModule
from generalist_control.training.settings import TrainingSettings

__all__ = [
    "DVC_METRICS",
    "closed_loop_scores",
    "dvc_metrics",
    "end_message",
    "check_models_dir",
    "log_inputs",
    "log_model",
]

#: ``metrics.json``: its key -> (the training's metric, whether stored as log10).
DVC_METRICS: dict[str, tuple[str, bool]] = {
    "val/loss": ("val/loss", False),
    "train/loss": ("train/loss", False),
    "val/log10_closed_loop": ("val/closed_loop", True),
    "closed_loop/log10_mse_mean": ("closed_loop/mse_mean", True),
    "closed_loop/diverged": ("closed_loop/diverged", False),
    "epochs": ("epochs", False),
    "n_parameters": ("n_parameters", False),
}


def check_models_dir(models_dir: Path) -> None:
    """Refuse, before training, a ``policy.ckpt`` or ``metrics.json`` no training wrote.

    Raises
    ------
    FileExistsError
        Naming the file and the fix (another ``paths.published_dir`` or ``run_dir``).
    """
    metrics = models_dir / "metrics.json"
    foreign = []
    if metrics.exists():
        try:
            keys = set(json.loads(metrics.read_text()))
        except (ValueError, TypeError, OSError):
            keys = {"not JSON"}
        if not keys <= set(DVC_METRICS):
            foreign.append(metrics)
    policy = models_dir / POLICY_FILE
    if policy.exists():
        try:
            load_policy(policy)
        except PolicyFileError as exc:
            if "older version" not in str(exc) and "policy format" not in str(exc):
                foreign.append(policy)  # an older policy of ours may be replaced
    if foreign:
        raise FileExistsError(
            f"refusing to overwrite {', '.join(map(str, foreign))}: not written by a training "
            "of this project. Nothing was changed; choose another folder "
            "(paths.published_dir, or run_dir for an unpublished run) or move the file away"
        )


def closed_loop_scores(
    settings: TrainingSettings, policy: Policy, meta: dict[str, Any]
) -> dict[str, float]:
    """``closed_loop/mse/<plant>``: GC-vs-LQI unit-step output MSE on ``closed_loop.systems``."""
    wanted = set(settings.closed_loop.systems)
    plants = [p for p in settings.plants if p.name in wanted and p.name in meta["tags"]]
    if not plants:
        return {}
    adapter = RuntimeAdapter(PolicyRuntime(policy, meta))
    mse = output_mse(adapter, plants, duration=settings.closed_loop.duration)
    scores = {f"closed_loop/mse/{k}": v for k, v in mse.items()}
    finite = [v for v in mse.values() if np.isfinite(v)]
    scores["closed_loop/mse_mean"] = float(np.mean(finite)) if finite else float("inf")
    scores["closed_loop/diverged"] = float(sum(not np.isfinite(v) for v in mse.values()))
    return scores


def log_model(
    policy: Policy,
    windows: dict[str, torch.Tensor],
    registered_name: str | None = None,
    tags: Mapping[str, str] | None = None,
) -> str | None:
    """Log the policy as an MLflow PyTorch model (``torch.export`` of :class:`FlatPolicy`).

    Eight ``windows`` are the signature's example; with ``registered_name``, a new registered
    version tagged with the run (and ``tags``), returned.
    """
    flat = FlatPolicy(policy).eval()
    n = min(8, windows["tag"].shape[0])
    x = torch.cat(
        [
            windows["state"][:n].flatten(1),
            windows["mask"][:n].flatten(1),
            windows["ref"][:n],
            windows["tag"][:n, None].float(),
        ],
        dim=1,
    ).numpy()
    with torch.no_grad():
        y = flat(torch.from_numpy(x)).numpy()
    with warnings.catch_warnings():
        # torch.export notes that nn.LSTM re-assigns its flat weight list while tracing
        warnings.filterwarnings("ignore", message=".*were assigned during export.*")
        info = mlflow.pytorch.log_model(
            flat,
            name="policy",
            signature=infer_signature(x, y),
            input_example=x,
            serialization_format="pt2",  # a traced graph: loading runs no pickled code
            metadata={"columns": flat_columns(policy.history, policy.width)},
            pip_requirements=[f"torch=={torch.__version__.split('+')[0]}", "numpy"],
            registered_model_name=registered_name or None,
        )
    version = info.registered_model_version
    if not registered_name or version is None:
        return None
    client, run = mlflow.MlflowClient(), mlflow.active_run()
    version_tags = dict(tags or {})
    if run is not None:  # the version names the run that made it
        run_tags = client.get_run(run.info.run_id).data.tags
        version_tags = {
            "run_id": run.info.run_id,
            "run_name": run_tags.get("mlflow.runName", ""),
            "data.content_hash": run_tags.get("data.content_hash", ""),
            **version_tags,
        }
    for key, value in version_tags.items():
        client.set_model_version_tag(registered_name, str(version), key, value)
    return str(version)


def log_inputs(settings: TrainingSettings, dm: DemoDataModule, n_params: int) -> None:
    """Params, tags, input artifacts and dataset of the active MLflow run; no password in them."""
    resolved = settings.resolved
    meta = dm.meta()
    params = {
        **training_run.training_params(resolved, list(settings.logger["params"] or [])),
        "data.content_hash": meta["content_hash"],
        "n_parameters": str(n_params),
    }
    training_run.log_params_once(params)
    tags = {
        "data.content_hash": meta["content_hash"],
        "data.dir": meta["data_dir"],
        "data.n_train_windows": str(meta["n_train"]),
        "data.n_val_windows": str(meta["n_val"]),
        "run_dir": str(settings.run_dir),
    }
    dvc_md5 = mlflow_utils.dvc_data_version(settings.data_dir)
    if dvc_md5:
        tags["data.dvc_md5"] = dvc_md5
    if settings.ckpt_path:
        tags["resumed_from"] = str(settings.ckpt_path)
    mlflow.set_tags(tags)
    mlflow.log_text(OmegaConf.to_yaml(OmegaConf.create(resolved)), "config/resolved.yaml")
    for path in sorted((settings.run_dir / ".hydra").glob("*.yaml")):
        mlflow.log_text(redact(path.read_text()), f"config/hydra/{path.name}")
    mlflow.log_dict(dm.manifest, "data/manifest.json")
    t = dm.split("train").tensors  # the training windows' schema: the run's dataset input
    with warnings.catch_warnings():
        # a local path matches two artifact-source classes of MLflow's registry alike
        warnings.filterwarnings("ignore", message=".*can be interpreted in multiple ways.*")
        dataset = from_numpy(
            {k: t[k].numpy() for k in ("state", "mask", "ref", "tag")},
            source=str(Path(meta["data_dir"]).resolve()),
            targets=t["target"].numpy(),
            name="demos",
            digest=meta["content_hash"].removeprefix("sha256:")[:36],
        )
    tags = {"content_hash": meta["content_hash"]}
    mlflow_utils.retry_on_clash(mlflow.log_input, dataset, context="training", tags=tags)


def dvc_metrics(metrics: Mapping[str, float]) -> dict[str, float]:
    """The headline numbers for ``metrics.json`` (:data:`DVC_METRICS`), 7 significant digits.

    Closed-loop errors as ``log10`` (``dvc metrics show`` rounds 1e-6 to 0).

    Examples
    --------
    >>> dvc_metrics({"val/loss": 0.0035093, "closed_loop/mse_mean": 1.82e-06, "epochs": 30})
    {'val/loss': 0.0035093, 'closed_loop/log10_mse_mean': -5.739929, 'epochs': 30}
    """
    out: dict[str, float] = {}
    for key, (name, log10) in DVC_METRICS.items():
        if name not in metrics:
            continue
        value = metrics[name]
        if log10:
            value = math.log10(value) if value > 0 else -math.inf
        out[key] = value if isinstance(value, int) else float(f"{value:.7g}")
    return out


def end_message(
    policy_path: Path, run_id: str, experiment: str, uri: str, version: str | None, name: str
) -> str:
    """The line a training ends with: the policy, the run, the registered model, the UI."""
    where = f"MLflow run {run_id} in experiment '{experiment}' ({redact(uri)})"
    registered = f"registered model {name} version {version}" if version else "not registered"
    if uri.startswith(("http://", "https://")):
        ui = f"open {redact(uri)}"
    else:
        ui = f"run: mlflow ui --backend-store-uri {redact(uri)}"
    return f"policy written to {policy_path}; {where}; {registered}; to browse it {ui}"
