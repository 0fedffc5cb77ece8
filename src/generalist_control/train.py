"""The train stage: demonstrations -> trained policy, logged to MLflow.

Run ``python train.py`` at the repository root (Hydra: e.g. ``model.hidden=64 experts=5``,
``experiment=paper``), ``gc-train``, or ``dvc repro train``. :func:`train` does the work;
:func:`main` only calls it. Outputs:

* ``<run_dir>/checkpoints/``: Lightning checkpoints (best on ``val/loss``, and ``last.ckpt``
  to resume with ``ckpt_path=<run_dir>/checkpoints/last.ckpt``);
* ``<paths.models_dir>/policy.ckpt`` (the best policy, loadable with
  :func:`generalist_control.policy.load_policy`) and ``metrics.json``;
* one MLflow run (see :mod:`generalist_control.mlflow_utils`).
"""

from __future__ import annotations

import json
import logging
import warnings
from datetime import datetime
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import mlflow
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from mlflow.models import infer_signature
from omegaconf import DictConfig, OmegaConf

from generalist_control import mlflow_utils
from generalist_control.datamodule import DemoDataModule
from generalist_control.lit_module import LitController
from generalist_control.model import (
    MODEL_DEFAULTS,
    controller_config,
    count_parameters,
    input_width,
)
from generalist_control.paths import HYDRA_CONFIG_PATH
from generalist_control.policy import FlatPolicy, Policy, flat_columns, load_policy, save_policy
from generalist_control.runtime import integral_facts

__all__ = ["job_models_dir", "main", "model_config", "train"]

log = logging.getLogger(__name__)

POLICY_FILE = "policy.ckpt"
METRICS_FILE = "metrics.json"


def _run_dir(cfg: DictConfig) -> Path:
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


def _write_json(path: Path, data: dict[str, Any]) -> None:
    """Atomic JSON; non-finite numbers (a diverged closed-loop score) become null."""
    clean = {k: v if not isinstance(v, float) or np.isfinite(v) else None for k, v in data.items()}
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(clean, indent=2, sort_keys=True) + "\n")
    tmp.replace(path)


def _closed_loop_scores(cfg: DictConfig, policy: Policy, meta: dict[str, Any]) -> dict[str, float]:
    """``closed_loop/mse/<plant>``: GC-vs-LQI unit-step output MSE on ``closed_loop.systems``.

    The ablation study's score (Section 7), computed right after training so that every
    sweep point carries it; plants the policy was not trained on are skipped.
    """
    spec = cfg.get("closed_loop") or {}
    wanted = set(spec.get("systems") or ())
    if not wanted:
        return {}
    from generalist_control.catalog import plants_from_config
    from generalist_control.evaluate import output_mse
    from generalist_control.runtime import PolicyRuntime

    plants = [p for p in plants_from_config(cfg.systems) if p.name in wanted]
    plants = [p for p in plants if p.name in meta["tags"]]
    if not plants:
        return {}
    runtime = PolicyRuntime(policy, meta)
    mse = output_mse(runtime, plants, duration=float(spec.get("duration", 15.0)))
    scores = {f"closed_loop/mse/{k}": v for k, v in mse.items()}
    finite = [v for v in mse.values() if np.isfinite(v)]
    scores["closed_loop/mse_mean"] = float(np.mean(finite)) if finite else float("inf")
    scores["closed_loop/diverged"] = float(sum(not np.isfinite(v) for v in mse.values()))
    return scores


def _dagger(cfg: DictConfig, meta: dict[str, Any]) -> L.Callback | None:
    """The DAgger callback for ``cfg.dagger`` (None when it is off or absent)."""
    spec = cfg.get("dagger")
    if not spec or not spec.get("enabled", False):
        return None
    from generalist_control.catalog import plants_from_config
    from generalist_control.dagger import DAggerCallback

    plants = [p for p in plants_from_config(cfg.systems) if p.name in meta["tags"]]
    kwargs = {k: v for k, v in OmegaConf.to_container(spec, resolve=True).items()}
    kwargs.pop("enabled")
    kwargs.setdefault("limit", float(cfg.data.amplitudes.limit))
    kwargs.setdefault("seed", int(cfg.seed or 0))
    if cfg.model.get("integral", False) and kwargs.get("takeover") == "bumpless":
        raise ValueError(
            "model.integral=true: DAgger must label from the integrator the policy sees; "
            "set dagger.takeover=tracked (or auto)"
        )
    return DAggerCallback(plants, **kwargs)


def _closed_loop_validation(cfg: DictConfig, meta: dict[str, Any]) -> L.Callback | None:
    """``val/closed_loop`` on every training plant (``closed_loop_val``; None when off)."""
    spec = cfg.get("closed_loop_val")
    if not spec or not spec.get("enabled", True):
        return None
    from generalist_control.catalog import plants_from_config
    from generalist_control.evaluate import ClosedLoopValidation

    plants = [p for p in plants_from_config(cfg.systems) if p.name in meta["tags"]]
    return ClosedLoopValidation(plants, list(spec.amplitudes), float(spec.duration))


def _callbacks(cfg: DictConfig, run_dir: Path) -> list[L.Callback]:
    callbacks = []
    for name, node in (cfg.get("callbacks") or {}).items():
        if node is None or "_target_" not in node:
            continue
        kwargs = {}
        if name == "model_checkpoint" and node.get("dirpath") is None:
            kwargs["dirpath"] = str(run_dir / "checkpoints")
        callbacks.append(hydra.utils.instantiate(node, **kwargs))
    return callbacks


def _log_model(policy: Policy, windows: dict[str, torch.Tensor]) -> None:
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


def model_config(cfg: DictConfig) -> dict[str, int]:
    """The network config of a training config: ``model.*``, ``experts`` and the window sizes.

    ``experts`` is a top-level key (``experts=5`` works as typed); ``history`` and ``horizon``
    come from the data config, so the network always matches the windows it is fed.
    """
    keys = set(MODEL_DEFAULTS) - {"experts", "state_dim", "history", "horizon"}
    return controller_config(
        **{k: v for k, v in cfg.model.items() if k in keys},
        experts=cfg.experts,
        history=cfg.data.history,
        horizon=cfg.data.horizon,
    )


def _check_resume(ckpt_path: str, meta: dict[str, Any]) -> None:
    old = torch.load(ckpt_path, map_location="cpu", weights_only=True)["hyper_parameters"]
    old_hash = old.get("meta", {}).get("content_hash")
    if old_hash != meta["content_hash"]:
        raise ValueError(
            f"checkpoint {ckpt_path} was trained on data {old_hash}, but "
            f"{meta['data_dir']} holds {meta['content_hash']}; resume on the same data"
        )


def _log_inputs(cfg: DictConfig, dm: DemoDataModule, n_params: int, run_dir: Path) -> None:
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


def train(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train the policy described by ``cfg``; return its metrics and the objects made.

    Parameters
    ----------
    cfg : DictConfig
        The composed primary config (``conf/config.yaml``).

    Returns
    -------
    metrics : dict
        ``val/loss`` and ``val/mse/<plant>`` of the best checkpoint, ``train/loss`` of the
        last epoch, ``n_parameters``, ``epochs``, ``global_step``.
    objects : dict
        ``trainer``, ``model`` (the LightningModule), ``datamodule``, ``policy`` (the best),
        ``run_id`` (MLflow), ``best_checkpoint``, ``policy_path``.

    Raises
    ------
    generalist_control.demos.MissingDataError
        Before anything is logged, if there is no dataset at ``paths.data_dir``.
    """
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    if cfg.get("seed") is not None:
        L.seed_everything(int(cfg.seed), workers=True)
    dm = DemoDataModule(
        cfg.paths.data_dir,
        cfg.data.history,
        cfg.data.horizon,
        seed=int(cfg.seed or 0),
        integral=bool(cfg.model.get("integral", False)),
        **cfg.loader,
    )
    dm.setup("fit")
    meta = {**dm.meta(), **integral_facts(list(dm.tags))}
    ckpt_path = cfg.get("ckpt_path")
    if ckpt_path:
        _check_resume(ckpt_path, meta)
    model_cfg = model_config(cfg)
    scheduler = cfg.model.get("scheduler")
    if scheduler is not None and "T_max" in scheduler and scheduler.T_max is None:
        scheduler = OmegaConf.merge(scheduler, {"T_max": int(cfg.trainer.max_epochs)})
    lit = LitController(
        model=model_cfg,
        optimizer=OmegaConf.to_container(cfg.model.optimizer, resolve=True),
        scheduler=OmegaConf.to_container(scheduler, resolve=True) if scheduler else None,
        meta=meta,
    )
    lit.policy.normaliser.fit(**dm.train_set.tensors)
    linear_init = cfg.model.get("linear_init", "zero")
    if linear_init not in ("zero", "lstsq"):
        raise ValueError(f"model.linear_init must be 'zero' or 'lstsq', got {linear_init!r}")
    if linear_init == "lstsq" and model_cfg["linear_head"] and not ckpt_path:
        residuals = lit.policy.fit_linear_head(**dm.train_set.tensors)
        names = {t: n for n, t in dm.tags.items()}
        worst = max(residuals, key=residuals.get)
        log.info(
            "linear head: least-squares start, worst relative residual %.3g (%s)",
            residuals[worst],
            names.get(worst, worst),
        )
    n_params = count_parameters(lit.policy)
    run_dir = _run_dir(cfg)
    callbacks = _callbacks(cfg, run_dir)
    ckpt_cb = next(c for c in callbacks if isinstance(c, L.pytorch.callbacks.ModelCheckpoint))
    epoch_logger = mlflow_utils.MLflowEpochLogger()
    dagger = _dagger(cfg, meta)
    extra = {"reload_dataloaders_every_n_epochs": 1} if dagger else {}
    own = [c for c in (dagger, _closed_loop_validation(cfg, meta)) if c is not None]
    trainer: L.Trainer = hydra.utils.instantiate(
        cfg.trainer,
        callbacks=[*callbacks, *own, epoch_logger],
        logger=False,
        default_root_dir=str(run_dir),
        **extra,
    )
    resume_id = mlflow_utils.run_id_from_checkpoint(ckpt_path) if ckpt_path else None

    with mlflow_utils.mlflow_run(cfg.logger, resume_run_id=resume_id) as run:
        run_id = epoch_logger.run_id = run.info.run_id
        _log_inputs(cfg, dm, n_params, run_dir)
        log.info("MLflow run %s (%s); %d parameters", run_id, mlflow.get_tracking_uri(), n_params)
        with warnings.catch_warnings():
            # batches are gathered from in-memory tensors: worker processes would only slow it
            warnings.filterwarnings("ignore", message=".*does not have many workers.*")
            trainer.fit(lit, datamodule=dm, ckpt_path=ckpt_path)
            best = ckpt_cb.best_model_path or ckpt_cb.last_model_path
            train_loss = float(trainer.callback_metrics.get("train/loss", float("nan")))
            trainer.validate(lit, datamodule=dm, ckpt_path=best, verbose=False)
        best_metrics = {
            k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")
        }
        metrics: dict[str, Any] = {
            **best_metrics,
            "train/loss": train_loss,
            "n_parameters": n_params,
            "epochs": int(trainer.current_epoch),
            "global_step": int(trainer.global_step),
        }
        policy, _ = load_policy(best)
        models_dir = job_models_dir(cfg)
        mlflow.set_tag("policy_dir", str(models_dir.resolve()))
        policy_meta = {**meta, "metrics": metrics, "mlflow_run_id": run_id}
        policy_path = save_policy(models_dir / POLICY_FILE, policy, policy_meta)
        metrics_path = models_dir / METRICS_FILE
        _write_json(metrics_path, metrics)

        best_step = trainer.current_epoch
        mlflow.log_metrics({f"best/{k}": v for k, v in best_metrics.items()}, step=best_step)
        mlflow.log_artifact(best, "checkpoints")
        mlflow.log_artifact(str(policy_path), "policy")
        mlflow.log_artifact(str(metrics_path), "policy")
        scores = _closed_loop_scores(cfg, policy, policy_meta)
        if scores:
            mlflow.log_metrics({k: v for k, v in scores.items() if np.isfinite(v)})
            metrics.update(scores)
            _write_json(metrics_path, metrics)
        if cfg.logger.get("log_model", True):
            _log_model(policy, dm.val_set.tensors)

    objects = {
        "trainer": trainer,
        "model": lit,
        "datamodule": dm,
        "policy": policy,
        "run_id": run_id,
        "best_checkpoint": best,
        "policy_path": policy_path,
    }
    return metrics, objects


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="config")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: train and return the optimised metric (``optimized_metric``)."""
    metrics, _ = train(cfg)
    return float(metrics.get(cfg.get("optimized_metric", "val/loss"), np.nan))


if __name__ == "__main__":
    main()
