"""Training: demonstrations -> trained policy, logged to MLflow.

:func:`train` does the work for the ``train`` stage (:mod:`generalist_control.train`, run
as ``python train.py``) and for every sweep job and Optuna trial. Outputs:

* ``<run_dir>/checkpoints/``: Lightning checkpoints (best on ``monitor``, and ``last.ckpt``,
  the last finished epoch, to resume with ``ckpt_path=<run_dir>/checkpoints/last.ckpt``);
* ``policy.ckpt`` (the best policy, loadable with
  :func:`generalist_control.model.policy.load_policy`) and ``metrics.json`` (headline
  numbers, :func:`.outputs.dvc_metrics`), in ``<run_dir>/models``, or in
  ``paths.published_dir`` (``models/``) when the run publishes (``publish=true``: the DVC
  stage); see :func:`.outputs.job_models_dir`;
* one MLflow run, opened by Lightning's ``MLFlowLogger``
  (:mod:`generalist_control.tracking.training_run`), and a new version of the registered
  model ``logger.registered_model_name``.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import warnings
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import mlflow
import numpy as np
import torch
from lightning.pytorch.loggers import MLFlowLogger
from omegaconf import DictConfig

from generalist_control.common.configs import as_dict
from generalist_control.common.jsonsafe import write_json
from generalist_control.common.secrets import redact
from generalist_control.deploy.facts import integral_facts
from generalist_control.model.bank import fit_model_rows
from generalist_control.model.network import count_parameters
from generalist_control.model.policy import POLICY_FILE, Policy, load_policy, save_policy
from generalist_control.plants.catalog import tag_count
from generalist_control.plants.plant import Plant
from generalist_control.tracking import training_run
from generalist_control.training import outputs
from generalist_control.training.dagger import DAggerCallback
from generalist_control.training.datamodule import DemoDataModule, WindowTensors
from generalist_control.training.family_set import (
    FamilySet,
    FamilyTraining,
    read_family_training,
    with_rows,
)
from generalist_control.training.lit_module import ImitationModule
from generalist_control.training.settings import TrainingSettings, read_training
from generalist_control.training.setup import (
    check_resume,
    closed_loop_validation,
    config_callbacks,
    dagger_callback,
    dagger_plants,
    included_plants,
    training_plants,
)

__all__ = ["METRICS_FILE", "train"]

log = logging.getLogger(__name__)

METRICS_FILE = "metrics.json"


def _data(
    cfg: DictConfig,
    settings: TrainingSettings,
    channels: tuple[str, ...],
    families: FamilySet | None,
) -> tuple[DemoDataModule, dict[str, Any]]:
    """The loaded, split data (the set's plants and the families') and the policy's meta."""
    dm = DemoDataModule(
        cfg.paths.data_dir,
        settings.history,
        settings.horizon,
        settings.loader,
        seed=settings.seed,
        plants=included_plants(cfg) + (families.names if families else []),
        channels=channels,
        families=families,
    )
    dm.setup("fit")
    facts = integral_facts(list(dm.tags))
    for key, more in (families.facts() if families else {}).items():
        facts[key] = {**facts[key], **more}
    return dm, {**dm.meta(), **facts}


def _families_spec(cfg: DictConfig) -> FamilyTraining | None:
    """``train_families`` read (None: the catalogue alone)."""
    node = cfg.train_families
    return read_family_training(None if node is None else as_dict(node))


def _tensors(split: WindowTensors | None) -> dict[str, torch.Tensor]:
    """The tensors of a split of the set-up data module."""
    if split is None:
        raise RuntimeError("the data module is not set up")
    return split.tensors


def _module(
    settings: TrainingSettings,
    dm: DemoDataModule,
    meta: dict[str, Any],
    resume: bool,
    plants: list[Plant],
) -> ImitationModule:
    """The Lightning module, its normaliser fitted, a per-tag table started by least squares.

    Rows a recipe computes from its plants' models (the card bank) come from ``plants``.
    """
    lit = ImitationModule(
        model=settings.model,
        optimizer=settings.optimizer,
        scheduler=settings.scheduler,
        meta=meta,
    )
    lit.policy.normaliser.fit(**_tensors(dm.train_set))
    fit_model_rows(lit.policy, plants)
    if lit.policy.net.table is not None and not resume:
        t = _tensors(dm.train_set)
        residuals = lit.policy.fit_table(t["state"], t["mask"], t["ref"], t["tag"], t["target"])
        names = {t: n for n, t in dm.tags.items()}
        worst = max(residuals, key=residuals.__getitem__)
        log.info(
            "per-tag table: least-squares start, worst relative residual %.3g (%s)",
            residuals[worst],
            names.get(worst, worst),
        )
    return lit


def _callbacks(
    cfg: DictConfig,
    settings: TrainingSettings,
    run_dir: Path,
    lit: ImitationModule,
    dm: DemoDataModule,
) -> tuple[list[L.Callback], L.pytorch.callbacks.ModelCheckpoint]:
    """The config's callbacks, DAgger and the closed-loop validation."""
    callbacks = config_callbacks(cfg, run_dir)
    ckpt_cb = next(c for c in callbacks if isinstance(c, L.pytorch.callbacks.ModelCheckpoint))
    plants = training_plants(cfg, dm.meta())
    channels = lit.policy.channels
    family = dm.families.plants if dm.families else []
    spec = _families_spec(cfg)
    turn, checked = (spec.dagger_plants, spec.closed_loop_plants) if spec else (0, 0)
    own = [
        dagger_callback(cfg, settings, dagger_plants(plants, dm.manifest), channels, family, turn),
        closed_loop_validation(settings, plants + family[:checked]),
    ]
    return [*callbacks, *(c for c in own if c is not None)], ckpt_cb


def _trainer(
    cfg: DictConfig, run_dir: Path, callbacks: list[L.Callback], mlf: MLFlowLogger
) -> L.Trainer:
    """The Lightning trainer with ``callbacks``, logging to ``mlf``'s run."""
    recorder = training_run.RunRecorder(str(mlf.run_id))
    dagger = any(isinstance(c, DAggerCallback) for c in callbacks)
    extra = {"reload_dataloaders_every_n_epochs": 1} if dagger else {}
    trainer: L.Trainer = hydra.utils.instantiate(
        cfg.trainer,
        callbacks=[*callbacks, recorder],
        logger=mlf,
        default_root_dir=str(run_dir),
        **extra,
    )
    return trainer


def _fit(
    trainer: L.Trainer,
    lit: ImitationModule,
    dm: DemoDataModule,
    ckpt_path: str | None,
    ckpt_cb: L.pytorch.callbacks.ModelCheckpoint,
) -> tuple[str, dict[str, Any]]:
    """Fit, then validate the best checkpoint; return its path and the metrics."""
    with warnings.catch_warnings():
        # batches are gathered from in-memory tensors: worker processes would only slow it
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        # what exists now (modules, data, trainer) lives through the fit: the collector's
        # full passes, a third of a second each, need not walk it; collectable again after
        gc.freeze()
        try:
            trainer.fit(lit, datamodule=dm, ckpt_path=ckpt_path)
        finally:
            gc.unfreeze()
        best = ckpt_cb.best_model_path or ckpt_cb.last_model_path
        train_loss = float(trainer.callback_metrics.get("train/loss", float("nan")))
        trainer.validate(lit, datamodule=dm, ckpt_path=best, verbose=False)
    best_metrics = {
        k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")
    }
    metrics: dict[str, Any] = {
        **best_metrics,
        "train/loss": train_loss,
        "n_parameters": count_parameters(lit.policy),
        "epochs": int(trainer.current_epoch),
        "global_step": int(trainer.global_step),
    }
    mlflow.log_metrics(
        {f"best/{k}": v for k, v in best_metrics.items()}, step=trainer.current_epoch
    )
    return best, metrics


def _check_fits(settings: TrainingSettings, ckpt_path: str, lit: ImitationModule) -> None:
    """Refuse, before any run is touched, a checkpoint whose weights do not fit ``lit``."""
    blob = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    saved, own = blob.get("state_dict", {}), lit.state_dict()
    bad = sorted(set(saved) ^ set(own))
    bad += [k for k in own if k in saved and tuple(saved[k].shape) != tuple(own[k].shape)]
    if not bad:
        return
    old = blob.get("hyper_parameters", {}).get("model", {})
    diff = {
        f"model.{k}": (old[k], v)
        for k, v in settings.model.items()
        if isinstance(old, dict) and k in old and old[k] != v
    }
    shown = "; ".join(f"{k}: checkpoint {a}, config {b}" for k, (a, b) in diff.items())
    fix = " ".join(f"{k}={a}" for k, (a, _) in diff.items()) or "the checkpoint's model config"
    raise ValueError(
        f"checkpoint {ckpt_path} does not fit the model this config builds"
        f" ({shown or 'same model config'}); parameters that differ: {', '.join(bad[:6])}"
        f"{' ...' if len(bad) > 6 else ''}. Resume with the checkpoint's settings ({fix}), "
        "or drop ckpt_path to start a new run"
    )


def _publish(
    cfg: DictConfig,
    best: str,
    metrics: dict[str, Any],
    meta: dict[str, Any],
    run_id: str,
    run_dir: Path,
) -> tuple[Policy, Path]:
    """Save the best policy and its metrics, log them to the run, add closed-loop scores."""
    policy, _ = load_policy(best)
    models_dir = outputs.job_models_dir(cfg, run_dir)
    mlflow.set_tag("policy_dir", str(models_dir.resolve()))
    policy_meta = {**meta, "metrics": metrics, "mlflow_run_id": run_id}
    policy_path = save_policy(models_dir / POLICY_FILE, policy, policy_meta)
    mlflow.log_artifact(best, "checkpoints")
    mlflow.log_artifact(str(policy_path), "policy")
    scores = outputs.closed_loop_scores(cfg, policy, policy_meta)
    if scores:
        mlflow.log_metrics({k: v for k, v in scores.items() if np.isfinite(v)})
        metrics.update(scores)
    metrics_path = write_json(models_dir / METRICS_FILE, outputs.dvc_metrics(metrics))
    mlflow.log_artifact(str(metrics_path), "policy")
    return policy, policy_path


def _prepare(
    cfg: DictConfig,
) -> tuple[TrainingSettings, DemoDataModule, dict[str, Any], ImitationModule]:
    """Config checked, threads and seed set, data loaded, module built; nothing logged yet."""
    outputs.scrub_hydra_files()
    settings = read_training(cfg)
    spec = _families_spec(cfg)
    families = FamilySet.load(spec.dirs, tag_count()) if spec else None
    settings = dataclasses.replace(settings, model=with_rows(settings.model, families))
    torch.set_num_threads(settings.threads)
    L.seed_everything(settings.seed, workers=True)
    ckpt_path = cfg.get("ckpt_path")
    with torch.random.fork_rng():  # the model config checked before the data is read
        channels = Policy(settings.model).channels
    dm, meta = _data(cfg, settings, channels, families)
    if ckpt_path:
        check_resume(ckpt_path, meta)
    plants = training_plants(cfg, meta) + (families.plants if families else [])
    lit = _module(settings, dm, meta, resume=bool(ckpt_path), plants=plants)
    if ckpt_path:
        _check_fits(settings, ckpt_path, lit)
        check_resume(ckpt_path, meta, settings.max_epochs)
    return settings, dm, meta, lit


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
        ``run_id`` and ``experiment`` (MLflow), ``registered_version`` (None when not
        registered), ``best_checkpoint``, ``policy_path``.

    Raises
    ------
    generalist_control.data.demos.MissingDataError
        Before anything is logged, if there is no dataset at ``paths.data_dir``.
    ValueError
        Before any run is opened, if ``ckpt_path`` holds other data or another model.
    """
    settings, dm, meta, lit = _prepare(cfg)
    ckpt_path = cfg.get("ckpt_path")
    n_params = count_parameters(lit.policy)
    run_dir = outputs.run_dir(cfg)
    outputs.check_models_dir(outputs.job_models_dir(cfg, run_dir))
    resume_id = training_run.run_id_from_checkpoint(ckpt_path) if ckpt_path else None
    callbacks, ckpt_cb = _callbacks(cfg, settings, run_dir, lit, dm)
    mlf = training_run.training_logger(cfg.logger, resume_run_id=resume_id)
    trainer = _trainer(cfg, run_dir, callbacks, mlf)
    with mlflow.start_run(run_id=mlf.run_id) as run:  # the fluent API on the logger's run
        run_id = run.info.run_id
        outputs.log_inputs(cfg, dm, n_params, run_dir)
        uri = mlflow.get_tracking_uri()
        log.info("MLflow run %s (%s); %d parameters", run_id, redact(uri), n_params)
        best, metrics = _fit(trainer, lit, dm, ckpt_path, ckpt_cb)
        policy, policy_path = _publish(cfg, best, metrics, meta, run_id, run_dir)
        name = cfg.logger.get("registered_model_name")
        version = None
        if cfg.logger.get("log_model", True):
            version = outputs.log_model(policy, _tensors(dm.val_set), name)
    experiment = mlflow.MlflowClient().get_experiment(run.info.experiment_id).name
    log.info(outputs.end_message(policy_path, run_id, experiment, uri, version, str(name)))
    objects = dict(trainer=trainer, model=lit, datamodule=dm, policy=policy, run_id=run_id)
    objects.update(experiment=experiment, registered_version=version, best_checkpoint=best)
    return metrics, {**objects, "policy_path": policy_path}
