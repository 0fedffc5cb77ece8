"""What a training run is built from: its plants, callbacks and resume checks."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch

from generalist_control.plants.definition import Plant
from generalist_control.plants.variants import make_variant
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
]


def dagger_plants(plants: list[Plant], manifest: dict[str, Any]) -> list[Plant]:
    """The plants DAgger rolls out on: ``plants`` and the data's variants of them.

    The variants are rebuilt from the factors the manifest records: the very plants the data
    stage simulated.
    """
    recorded = manifest.get("variants") or {}
    out: list[Plant] = []
    for p in plants:
        out.append(p)
        out.extend(make_variant(p, v["factors"]) for v in recorded.get(p.name, {}).get("kept", []))
    return out


def dagger_callback(
    settings: TrainingSettings,
    plants: list[Plant],
    channels: tuple[str, ...],
    rotating: Sequence[Plant] = (),
    per_round: int = 0,
) -> L.Callback | None:
    """The DAgger callback of ``settings.dagger`` on ``plants`` (None when it is off).

    ``rotating`` plants (a family's) join each round, ``per_round`` at a time, in turn.
    """
    spec = settings.dagger
    if spec is None:
        return None
    data = settings.rollout_data
    sampler = RolloutSampler(
        plants,
        spec.sampler,
        limit=data.amplitude_limit,
        families=data.families,
        seed=settings.seed,
        variant_range=data.variant_range,
        variant_tries=data.variant_tries,
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


def config_callbacks(nodes: Sequence[Mapping[str, Any]], run_dir: Path) -> list[L.Callback]:
    """The callbacks named in ``callbacks``; ``dirpath: null`` becomes ``<run_dir>/checkpoints``.

    Lightning would otherwise put checkpoints under the logger's run.
    """
    callbacks = []
    for node in nodes:
        kwargs = {}
        if "dirpath" in node and node["dirpath"] is None:
            kwargs["dirpath"] = str(run_dir / "checkpoints")
        callbacks.append(hydra.utils.instantiate(node, **kwargs))
    return callbacks


def check_resume(ckpt_path: str, meta: dict[str, Any], max_epochs: int | None = None) -> None:
    """Refuse to resume from a checkpoint of other data, other plants, or nothing left to do.

    Raises
    ------
    ValueError
        Other data (content hash), another plant set, or (given ``max_epochs``) all epochs
        already run, so that a resume would only publish the old checkpoint.
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
