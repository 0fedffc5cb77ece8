"""Training: demonstrations -> trained policy, one MLflow run (docs/training.md, "Outputs").

:func:`train` is the work of the ``train`` stage, every sweep job and every Optuna trial.
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import warnings
from pathlib import Path
from typing import Any, cast

import hydra
import lightning as L
import mlflow
import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.loggers import MLFlowLogger
from lightning.pytorch.utilities.exceptions import SIGTERMException

from generalist_control.common.hydra_redact import scrub_hydra_files
from generalist_control.common.jsonsafe import write_json
from generalist_control.common.secrets import redact
from generalist_control.deploy.runtime_plants import integral_facts
from generalist_control.model.bank import fit_model_rows
from generalist_control.model.network import count_parameters
from generalist_control.model.policy import (
    POLICY_FILE,
    Policy,
    load_policy,
    policy_sha256,
    save_policy,
)
from generalist_control.plants.catalog import tag_count
from generalist_control.plants.definition import Plant
from generalist_control.simulation.comparison import ClosedLoopScore
from generalist_control.tracking import training_run
from generalist_control.tracking.mlflow_utils import POLICY_HASH_TAG
from generalist_control.training import outputs
from generalist_control.training.callbacks import (
    ClosedLoopValidation,
    DAggerCallback,
    dagger_plants,
)
from generalist_control.training.datamodule import DemoDataModule
from generalist_control.training.family_set import FamilySet, with_rows
from generalist_control.training.labeller import ExpertLabeller
from generalist_control.training.lit_module import ImitationModule
from generalist_control.training.sampler import RolloutSampler
from generalist_control.training.settings import TrainingSettings
from generalist_control.training.unseen_draw import UnseenDraw

__all__ = ["METRICS_FILE", "train"]

log = logging.getLogger(__name__)

METRICS_FILE = "metrics.json"


def _trained(settings: TrainingSettings, dm: DemoDataModule) -> tuple[list[Plant], list[Plant]]:
    """The plants the data holds: the set's, and the families'."""
    family = dm.families.plants if dm.families else []
    return [p for p in settings.plants if p.name in dm.tags], family


def _callbacks(
    settings: TrainingSettings, lit: ImitationModule, dm: DemoDataModule
) -> list[L.Callback]:
    """The config's callbacks, then DAgger's and the closed-loop validation's (when on)."""
    callbacks = [hydra.utils.instantiate(node) for node in settings.callbacks]
    plants, family = _trained(settings, dm)
    spec = dm.families.spec if dm.families else None
    turn, checked = (spec.dagger_plants, spec.closed_loop_plants) if spec else (0, 0)
    if (dagger := settings.dagger) is not None:  # a family's plants join in turn
        versions = dagger_plants(plants, dm.manifest)
        pick = hydra.utils.instantiate(spec.dagger_pick) if spec and spec.dagger_pick else None
        sampler = RolloutSampler(
            versions, dagger.sampler, settings.rollout_data, settings.seed, family, turn, pick
        )
        labeller = ExpertLabeller(
            dagger.labeller, settings.history, settings.horizon, lit.policy.channels
        )
        callbacks.append(DAggerCallback(sampler, labeller, dagger))
    if (val := settings.closed_loop_val) is not None:
        amplitudes = list(val.amplitudes)
        score = ClosedLoopScore(plants + family[:checked], amplitudes, val.duration)
        unseen = None
        if spec is not None and spec.validation is not None:
            draw = UnseenDraw.draw(spec.validation, lit.policy)
            unseen = draw, ClosedLoopScore(draw.plants, amplitudes, val.duration)
        callbacks.append(ClosedLoopValidation(score, unseen))
    return callbacks


def _trainer(
    settings: TrainingSettings, callbacks: list[L.Callback], mlf: MLFlowLogger
) -> L.Trainer:
    """The Lightning trainer with ``callbacks``, logging to ``mlf``'s run."""
    recorder = training_run.RunRecorder(str(mlf.run_id))
    extra = {"reload_dataloaders_every_n_epochs": 1} if settings.dagger else {}
    trainer: L.Trainer = hydra.utils.instantiate(
        settings.trainer,
        callbacks=[*callbacks, recorder],
        logger=mlf,
        default_root_dir=str(settings.run_dir),
        **extra,
    )
    return trainer


def _fit(
    trainer: L.Trainer, lit: ImitationModule, dm: DemoDataModule, ckpt_path: str | None
) -> tuple[str, dict[str, Any]]:
    """Fit, then validate the best checkpoint; return its path and the metrics."""
    with warnings.catch_warnings():
        # batches are gathered from in-memory tensors: workers would only slow it
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        trainer.fit(lit, datamodule=dm, ckpt_path=ckpt_path)
        ckpt_cb = cast(ModelCheckpoint, trainer.checkpoint_callback)  # the config's first
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


def _stopped(exc: SystemExit, trainer: L.Trainer) -> int | None:
    """The exit status of a training stopped by a signal (Lightning exits 0 or 1), else None."""
    if isinstance(exc, SIGTERMException):
        return 128 + signal.SIGTERM
    if trainer.interrupted:
        return 128 + signal.SIGINT
    return None


def _check_resume(
    settings: TrainingSettings, ckpt_path: str, meta: dict[str, Any], lit: ImitationModule
) -> None:
    """Refuse a checkpoint of other data, plants or model, or with no epoch left to train."""
    blob = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    old = blob.get("hyper_parameters", {}).get("meta", {})
    if old.get("content_hash") != meta["content_hash"]:
        raise ValueError(
            f"checkpoint {ckpt_path} was trained on data {old.get('content_hash')}, but "
            f"{meta['data_dir']} holds {meta['content_hash']}; resume on the same data"
        )
    if sorted(old.get("tags", {})) != sorted(meta["tags"]):
        raise ValueError(
            f"checkpoint {ckpt_path} was trained on the plants {sorted(old.get('tags', {}))}, "
            f"this config's set is {sorted(meta['tags'])}: resume with the same systems "
            "(systems, systems.include), or drop ckpt_path to start a new run"
        )
    saved, own = blob.get("state_dict", {}), lit.state_dict()
    bad = sorted(set(saved) ^ set(own))
    bad += [k for k in own if k in saved and tuple(saved[k].shape) != tuple(own[k].shape)]
    if bad:
        old_model = blob.get("hyper_parameters", {}).get("model", {})
        diff = {
            f"model.{k}": (old_model[k], v)
            for k, v in settings.model.items()
            if isinstance(old_model, dict) and k in old_model and old_model[k] != v
        }
        shown = "; ".join(f"{k}: checkpoint {a}, config {b}" for k, (a, b) in diff.items())
        fix = " ".join(f"{k}={a}" for k, (a, _) in diff.items()) or "the checkpoint's model config"
        raise ValueError(
            f"checkpoint {ckpt_path} does not fit the model this config builds"
            f" ({shown or 'same model config'}); parameters that differ: {', '.join(bad[:6])}"
            f"{' ...' if len(bad) > 6 else ''}. Resume with the checkpoint's settings ({fix}), "
            "or drop ckpt_path to start a new run"
        )
    done = int(blob.get("epoch", -1)) + 1
    if done >= settings.max_epochs:
        raise ValueError(
            f"checkpoint {ckpt_path} has finished {done} epochs and trainer.max_epochs is "
            f"{settings.max_epochs}: there is nothing left to train; raise trainer.max_epochs, "
            "or drop ckpt_path to start a new run"
        )


def _publish(
    settings: TrainingSettings, best: str, metrics: dict[str, Any], meta: dict[str, Any]
) -> tuple[Policy, Path]:
    """Save the best policy and its metrics, log them (the run tagged with the file's hash)."""
    policy, _ = load_policy(best)
    models_dir = settings.models_dir
    policy_meta = {**meta, "metrics": metrics}
    policy_path = save_policy(models_dir / POLICY_FILE, policy, policy_meta)
    mlflow.set_tags(
        {"policy_dir": str(models_dir.resolve()), POLICY_HASH_TAG: policy_sha256(policy_path)}
    )
    mlflow.log_artifact(best, "checkpoints")
    mlflow.log_artifact(str(policy_path), "policy")
    scores = outputs.closed_loop_scores(settings, policy, policy_meta)
    if scores:
        mlflow.log_metrics({k: v for k, v in scores.items() if np.isfinite(v)})
        metrics.update(scores)
    metrics_path = write_json(models_dir / METRICS_FILE, outputs.dvc_metrics(metrics))
    mlflow.log_artifact(str(metrics_path), "policy")
    return policy, policy_path


def _prepare(
    settings: TrainingSettings,
) -> tuple[TrainingSettings, DemoDataModule, dict[str, Any], ImitationModule]:
    """Data loaded, module built (normaliser fitted, then model rows), resume checked.

    Threads and seed are set first; nothing is logged yet.
    """
    scrub_hydra_files()
    torch.set_num_threads(settings.threads)
    L.seed_everything(settings.seed, workers=True)
    spec = settings.families
    families = FamilySet.load(spec.dirs, tag_count(), spec) if spec else None
    settings = dataclasses.replace(settings, model=with_rows(settings.model, families))
    with torch.random.fork_rng():  # the model config checked before the data is read
        channels = Policy(settings.model).channels
    plants = settings.trained_names + (families.names if families else [])
    dm = DemoDataModule(
        settings.data_dir, settings.history, settings.horizon, settings.loader,
        seed=settings.seed, plants=plants, channels=channels, families=families,
    )  # fmt: skip
    dm.setup("fit")
    meta = {**dm.meta(), **integral_facts(dm.tags, families.plants if families else ())}
    if families:
        meta["families"] = families.record()
    lit = ImitationModule(settings.model, settings.optimizer, settings.scheduler, meta)
    lit.policy.normaliser.fit(**dm.split("train").tensors)
    fit_model_rows(lit.policy, [p for group in _trained(settings, dm) for p in group])
    if settings.ckpt_path:
        _check_resume(settings, settings.ckpt_path, meta, lit)
    return settings, dm, meta, lit


def train(settings: TrainingSettings) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train the policy ``settings`` describe; return its metrics and the objects made.

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
    generalist_control.data.demos.MissingDataError, ValueError
        Before any run is opened: no dataset at ``paths.data_dir``; a ``ckpt_path`` of other
        data or another model.
    SystemExit
        143 (SIGTERM) or 130 (Ctrl-C) when a signal stops the fit: the run ends KILLED.
    """
    settings, dm, meta, lit = _prepare(settings)
    ckpt_path = settings.ckpt_path
    n_params = count_parameters(lit.policy)
    outputs.check_models_dir(settings.models_dir)
    resume_id = training_run.run_id_from_checkpoint(ckpt_path) if ckpt_path else None
    callbacks = _callbacks(settings, lit, dm)
    mlf = training_run.training_logger(settings.logger, resume_run_id=resume_id)
    trainer = _trainer(settings, callbacks, mlf)
    logger = settings.logger
    with training_run.logger_run(mlf) as run:  # the fluent API on the logger's run
        run_id = run.info.run_id
        outputs.log_inputs(settings, dm, n_params)
        uri = mlflow.get_tracking_uri()
        log.info("MLflow run %s (%s); %d parameters", run_id, redact(uri), n_params)
        try:
            best, metrics = _fit(trainer, lit, dm, ckpt_path)
        except SystemExit as exc:
            status = _stopped(exc, trainer)
            if status is None:
                raise
            mlflow.end_run("KILLED")
            log.error("training stopped by a signal: run %s KILLED, no policy written", run_id)
            raise SystemExit(status) from None
        policy, policy_path = _publish(settings, best, metrics, meta)
        name = logger["registered_model_name"]
        version = None
        if logger["log_model"]:
            version = outputs.log_model(policy, dm.split("val").tensors, name)
    experiment = mlflow.MlflowClient().get_experiment(run.info.experiment_id).name
    log.info(outputs.end_message(policy_path, run_id, experiment, uri, version, str(name)))
    objects = dict(trainer=trainer, model=lit, datamodule=dm, policy=policy, run_id=run_id)
    objects.update(experiment=experiment, registered_version=version, best_checkpoint=best)
    return metrics, {**objects, "policy_path": policy_path}
