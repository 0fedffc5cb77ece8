"""What a training run leaves behind: the policy file, metrics, and its MLflow record."""

from __future__ import annotations

import warnings
from datetime import datetime
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from mlflow.models import infer_signature
from omegaconf import DictConfig, OmegaConf

from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.flat import FlatPolicy, flat_columns
from generalist_control.model.network import input_width
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import plants_from_config
from generalist_control.simulation.comparison import output_mse
from generalist_control.tracking import mlflow_utils
from generalist_control.training.datamodule import DemoDataModule

__all__ = [
    "closed_loop_scores",
    "job_models_dir",
    "log_inputs",
    "log_model",
    "run_dir",
]


def run_dir(cfg: DictConfig) -> Path:
    """Where this run's checkpoints go: ``run_dir``, Hydra's output dir, or a new one."""
    if cfg.get("run_dir"):
        return Path(cfg.run_dir)
    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return Path("outputs/train") / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")


def job_models_dir(cfg: DictConfig) -> Path:
    """Where this run writes ``policy.ckpt``: ``paths.models_dir``, except in a multirun.

    Each job of a Hydra multirun (a sweep) writes to ``<its output dir>/models`` so that
    the jobs overwrite neither each other's model nor the DVC output ``models/``; a
    ``paths.models_dir=...`` on the command line still wins.
    """
    if HydraConfig.initialized():
        hc = HydraConfig.get()
        given = any(o.startswith("paths.models_dir=") for o in hc.overrides.task)
        if hc.mode == RunMode.MULTIRUN and not given:
            return Path(hc.runtime.output_dir) / "models"
    return Path(cfg.paths.models_dir)


def closed_loop_scores(cfg: DictConfig, policy: Policy, meta: dict[str, Any]) -> dict[str, float]:
    """``closed_loop/mse/<plant>``: GC-vs-LQI unit-step output MSE on ``closed_loop.systems``.

    The ablation study's score (Section 7), computed right after training so that every
    sweep point carries it; plants the policy was not trained on are skipped.
    """
    spec = cfg.get("closed_loop") or {}
    wanted = set(spec.get("systems") or ())
    if not wanted:
        return {}
    plants = [p for p in plants_from_config(cfg.systems) if p.name in wanted]
    plants = [p for p in plants if p.name in meta["tags"]]
    if not plants:
        return {}
    adapter = RuntimeAdapter(PolicyRuntime(policy, meta))
    mse = output_mse(adapter, plants, duration=float(spec.get("duration", 15.0)))
    scores = {f"closed_loop/mse/{k}": v for k, v in mse.items()}
    finite = [v for v in mse.values() if np.isfinite(v)]
    scores["closed_loop/mse_mean"] = float(np.mean(finite)) if finite else float("inf")
    scores["closed_loop/diverged"] = float(sum(not np.isfinite(v) for v in mse.values()))
    return scores


def log_model(policy: Policy, windows: dict[str, torch.Tensor]) -> None:
    """Log the best policy as an MLflow PyTorch model (``torch.export``, one flat input).

    The input is float32 (B, F) with the columns of :func:`flat_columns`, which are also
    stored in the model's metadata; the output is the control sequence (B, horizon).
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
    c = policy.config
    with warnings.catch_warnings():
        # torch.export notes that nn.LSTM re-assigns its flat weight list while tracing
        warnings.filterwarnings("ignore", message=".*were assigned during export.*")
        mlflow.pytorch.log_model(
            flat,
            name="policy",
            signature=infer_signature(x, y),
            input_example=x,
            serialization_format="pt2",  # a traced graph: loading runs no pickled code
            metadata={"columns": flat_columns(c["history"], input_width(c))},
            pip_requirements=[f"torch=={torch.__version__.split('+')[0]}", "numpy"],
        )


def log_inputs(cfg: DictConfig, dm: DemoDataModule, n_params: int, run_dir: Path) -> None:
    """Params, tags and input artifacts of the active MLflow run."""
    resolved = OmegaConf.to_container(cfg, resolve=True)
    params = {**mlflow_utils.flatten_params(resolved), "n_parameters": str(n_params)}
    mlflow_utils.log_params_once(params)
    meta = dm.meta()
    tags = {
        "data.content_hash": meta["content_hash"],
        "data.dir": meta["data_dir"],
        "data.n_train_windows": str(meta["n_train"]),
        "data.n_val_windows": str(meta["n_val"]),
        "run_dir": str(run_dir),
    }
    dvc_md5 = mlflow_utils.dvc_data_version(cfg.paths.data_dir)
    if dvc_md5:
        tags["data.dvc_md5"] = dvc_md5
    if cfg.get("ckpt_path"):
        tags["resumed_from"] = str(cfg.ckpt_path)
    mlflow.set_tags(tags)
    mlflow.log_text(OmegaConf.to_yaml(cfg, resolve=True), "config/resolved.yaml")
    if (run_dir / ".hydra").is_dir():
        mlflow.log_artifacts(str(run_dir / ".hydra"), "config/hydra")
    mlflow.log_dict(dm.manifest, "data/manifest.json")
