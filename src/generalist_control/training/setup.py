"""What a training run is built from: its plants, callbacks and resume checks."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch
from omegaconf import DictConfig

from generalist_control.common.configs import as_dict
from generalist_control.data.generation import enabled_families
from generalist_control.plants.catalog import plants_from_config
from generalist_control.plants.plant import Plant
from generalist_control.plants.variants import DEFAULT_RANGE, make_variant
from generalist_control.simulation.comparison import ClosedLoopScore
from generalist_control.training.callbacks import ClosedLoopValidation
from generalist_control.training.dagger import DAggerCallback
from generalist_control.training.labeller import ExpertLabeller
from generalist_control.training.sampler import RolloutSampler
from generalist_control.training.settings import TrainingSettings

__all__ = [
    "check_resume",
    "closed_loop_validation",
    "config_callbacks",
    "dagger_callback",
    "dagger_plants",
    "included_plants",
    "training_plants",
]


def included_plants(cfg: DictConfig) -> list[str]:
    """The plants of ``cfg.systems`` (with ``systems.include``: those it keeps), less ``held_out``.

    The data module trains and validates on these plants only, and refuses data that lacks
    one of them, so a run logged as ``systems.name=paper`` trained on the paper's plants.
    ``held_out`` (the held-out protocol, ``beyond/dvc.yaml:unseen``) names plants of the set
    that training never sees.

    Raises
    ------
    generalist_control.plants.catalog.UnknownPlantError
        If ``include`` names a plant that is not in the set.
    ValueError
        If ``held_out`` names a plant that is not in the set, or every plant of it.
    """
    names = [p.name for p in plants_from_config(cfg.systems)]
    held = [str(h) for h in (cfg.get("held_out") or [])]
    unknown = [h for h in held if h not in names]
    if unknown:
        raise ValueError(
            f"held_out names {unknown}, which the plant set (systems) does not hold; it holds "
            f"{names}"
        )
    kept = [n for n in names if n not in held]
    if not kept:
        raise ValueError(f"held_out={held} leaves no plant of the set to train on")
    return kept


def training_plants(cfg: DictConfig, meta: dict[str, Any]) -> list[Plant]:
    """The plants of ``cfg.systems`` that the data holds (``meta["tags"]``)."""
    return [p for p in plants_from_config(cfg.systems) if p.name in meta["tags"]]


def dagger_plants(plants: list[Plant], manifest: dict[str, Any]) -> list[Plant]:
    """The plants DAgger rolls out on: ``plants`` and, with variant data, their variants.

    With variant data the policy must also recover on the variants it imitates, so each
    training plant's kept variants join the rollouts, rebuilt from the factors the data's
    manifest records (:func:`~generalist_control.plants.variants.make_variant`: the very
    plants the data stage simulated); each is labelled by its own LQI expert.
    """
    recorded = manifest.get("variants") or {}
    out: list[Plant] = []
    for p in plants:
        out.append(p)
        out.extend(make_variant(p, v["factors"]) for v in recorded.get(p.name, {}).get("kept", []))
    return out


def dagger_callback(
    cfg: DictConfig,
    settings: TrainingSettings,
    plants: list[Plant],
    channels: tuple[str, ...],
    rotating: Sequence[Plant] = (),
    per_round: int = 0,
) -> L.Callback | None:
    """The DAgger callback of ``settings.dagger`` on ``plants`` (None when it is off).

    ``plants`` are the training plant versions (:func:`dagger_plants`); the sampler takes
    the data's amplitude limit, families and variant range from ``cfg.data``. ``rotating``
    plants (a family's) join each round ``per_round`` at a time, in turn.
    """
    spec = settings.dagger
    if spec is None:
        return None
    data = as_dict(cfg.data)
    block = data.get("variants") or {}  # fresh variants: the data's range and tries
    sampler = RolloutSampler(
        plants,
        spec.sampler,
        limit=float(data["amplitudes"]["limit"]),
        families=enabled_families(data),
        seed=settings.seed,
        variant_range=float(block.get("range", DEFAULT_RANGE)),
        variant_tries=int(block.get("max_tries", 10)),
        rotating=rotating,
        per_round=per_round,
    )
    labeller = ExpertLabeller(spec.labeller, settings.history, settings.horizon, channels)
    return DAggerCallback(sampler, labeller, spec)


def closed_loop_validation(settings: TrainingSettings, plants: list[Plant]) -> L.Callback | None:
    """``val/closed_loop`` on every training plant (``closed_loop_val``; None when off)."""
    spec = settings.closed_loop_val
    if spec is None:
        return None
    return ClosedLoopValidation(ClosedLoopScore(plants, list(spec.amplitudes), spec.duration))


def config_callbacks(cfg: DictConfig, run_dir: Path) -> list[L.Callback]:
    """The callbacks named in ``cfg.callbacks`` (checkpoints go to ``<run_dir>/checkpoints``).

    A callback with ``dirpath: null`` (both checkpoint callbacks) gets that directory:
    Lightning would otherwise put it under the logger's run (``<exp_id>/<run_id>``).
    """
    callbacks = []
    for node in (cfg.get("callbacks") or {}).values():
        if node is None or "_target_" not in node:
            continue
        kwargs = {}
        if "dirpath" in node and node.get("dirpath") is None:
            kwargs["dirpath"] = str(run_dir / "checkpoints")
        callbacks.append(hydra.utils.instantiate(node, **kwargs))
    return callbacks


def check_resume(ckpt_path: str, meta: dict[str, Any], max_epochs: int | None = None) -> None:
    """Refuse to resume from a checkpoint of other data, other plants, or nothing left to do.

    Raises
    ------
    ValueError
        If the checkpoint was trained on data with another content hash, on another plant
        set (``systems``), or (given ``max_epochs``) has already run ``trainer.max_epochs``
        epochs, so that a resume would train nothing and publish the old run's checkpoint;
        each message says what to do.
    """
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
    done = int(blob.get("epoch", -1)) + 1
    if max_epochs is not None and done >= max_epochs:
        raise ValueError(
            f"checkpoint {ckpt_path} has finished {done} epochs and trainer.max_epochs is "
            f"{max_epochs}: there is nothing left to train; raise trainer.max_epochs, or "
            "drop ckpt_path to start a new run"
        )
