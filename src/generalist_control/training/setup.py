"""What a training run is built from: the network config, callbacks, and resume checks."""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import hydra
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

from generalist_control.common.configs import as_dict
from generalist_control.data.generation import enabled_families
from generalist_control.model.network import MODEL_DEFAULTS, network_config
from generalist_control.plants.catalog import plants_from_config
from generalist_control.plants.plant import Plant
from generalist_control.training.callbacks import ClosedLoopValidation
from generalist_control.training.dagger_callback import DAggerCallback

__all__ = [
    "check_resume",
    "closed_loop_validation",
    "config_callbacks",
    "dagger_callback",
    "included_plants",
    "model_config",
    "training_plants",
]


def model_config(cfg: DictConfig) -> dict[str, int]:
    """The network config of a training config: ``model.*``, ``experts`` and the window sizes.

    ``experts`` is a top-level key (``experts=5`` works as typed); ``history`` and ``horizon``
    come from the data config, so the network always matches the windows it is fed.

    Raises
    ------
    ValueError
        If a value is not of its type (``model.hidden=32.9``, ``experts=2.5``: nothing is
        rounded) or out of range; see :func:`~generalist_control.model.network.network_config`.
    """
    keys = set(MODEL_DEFAULTS) - {"experts", "state_dim", "history", "horizon"}
    return network_config(
        **{k: v for k, v in cfg.model.items() if k in keys},
        experts=cfg.experts,
        history=cfg.data.history,
        horizon=cfg.data.horizon,
    )


def included_plants(cfg: DictConfig) -> list[str] | None:
    """The plants ``systems.include`` keeps (checked against the set); None without it.

    The data module then trains and validates on these plants only, so the include list
    means the same with DAgger and the closed-loop check off as with them on.

    Raises
    ------
    generalist_control.plants.catalog.UnknownPlantError
        If ``include`` names a plant that is not in the set.
    """
    if not cfg.systems.get("include"):
        return None
    return [p.name for p in plants_from_config(cfg.systems)]


def training_plants(cfg: DictConfig, meta: dict[str, Any]) -> list[Plant]:
    """The plants of ``cfg.systems`` that the data holds (``meta["tags"]``)."""
    return [p for p in plants_from_config(cfg.systems) if p.name in meta["tags"]]


def dagger_callback(cfg: DictConfig, plants: list[Plant]) -> L.Callback | None:
    """The DAgger callback for ``cfg.dagger`` (None when it is off or absent)."""
    spec = cfg.get("dagger")
    if not spec or not spec.get("enabled", False):
        return None
    kwargs = cast(dict[str, Any], OmegaConf.to_container(spec, resolve=True))
    kwargs.pop("enabled")
    kwargs.setdefault("limit", float(cfg.data.amplitudes.limit))
    kwargs.setdefault("seed", int(cfg.seed or 0))
    families = kwargs.pop("families", False)
    kwargs["families"] = enabled_families(as_dict(cfg.data)) if families else None
    if cfg.model.get("integral", False) and kwargs.get("takeover") == "bumpless":
        raise ValueError(
            "model.integral=true: DAgger must label from the integrator the policy sees; "
            "set dagger.takeover=tracked (or auto)"
        )
    return DAggerCallback(plants, **kwargs)


def closed_loop_validation(cfg: DictConfig, plants: list[Plant]) -> L.Callback | None:
    """``val/closed_loop`` on every training plant (``closed_loop_val``; None when off)."""
    spec = cfg.get("closed_loop_val")
    if not spec or not spec.get("enabled", True):
        return None
    return ClosedLoopValidation(plants, list(spec.amplitudes), float(spec.duration))


def config_callbacks(cfg: DictConfig, run_dir: Path) -> list[L.Callback]:
    """The callbacks named in ``cfg.callbacks`` (checkpoints go to ``<run_dir>/checkpoints``)."""
    callbacks = []
    for name, node in (cfg.get("callbacks") or {}).items():
        if node is None or "_target_" not in node:
            continue
        kwargs = {}
        if name == "model_checkpoint" and node.get("dirpath") is None:
            kwargs["dirpath"] = str(run_dir / "checkpoints")
        callbacks.append(hydra.utils.instantiate(node, **kwargs))
    return callbacks


def check_resume(ckpt_path: str, meta: dict[str, Any]) -> None:
    """Refuse to resume from a checkpoint trained on other data."""
    old = torch.load(ckpt_path, map_location="cpu", weights_only=True)["hyper_parameters"]
    old_hash = old.get("meta", {}).get("content_hash")
    if old_hash != meta["content_hash"]:
        raise ValueError(
            f"checkpoint {ckpt_path} was trained on data {old_hash}, but "
            f"{meta['data_dir']} holds {meta['content_hash']}; resume on the same data"
        )
