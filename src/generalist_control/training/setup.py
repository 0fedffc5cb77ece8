"""What a training run is built from: the network config, callbacks, and resume checks."""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import hydra
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

from generalist_control.common.configs import as_dict
from generalist_control.common.schema import require_fraction, require_int, require_nonnegative
from generalist_control.data.generation import enabled_families
from generalist_control.model.network import MODEL_DEFAULTS, network_config
from generalist_control.plants.catalog import plants_from_config
from generalist_control.plants.plant import Plant
from generalist_control.plants.variants import DEFAULT_RANGE, make_variant
from generalist_control.training.callbacks import ClosedLoopValidation
from generalist_control.training.dagger_callback import DAggerCallback
from generalist_control.training.rest import RestPenalty

__all__ = [
    "check_resume",
    "closed_loop_validation",
    "config_callbacks",
    "dagger_callback",
    "identity_clean_fit",
    "identity_loss",
    "identity_noise",
    "included_plants",
    "model_config",
    "plant_versions",
    "rest_penalty",
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
    derived = {"unknown_tag", "identity_head"}  # from tag_dropout and identity_loss
    keys = set(MODEL_DEFAULTS) - {"experts", "state_dim", "history", "horizon", *derived}
    return network_config(
        **{k: v for k, v in cfg.model.items() if k in keys},
        unknown_tag=tag_dropout(cfg) > 0,
        identity_head=identity_loss(cfg) > 0,
        experts=cfg.experts,
        history=cfg.data.history,
        horizon=cfg.data.horizon,
    )


def tag_dropout(cfg: DictConfig) -> float:
    """``model.tag_dropout``, checked: the share of training windows without their tag.

    Raises
    ------
    ValueError
        If it is not a number in [0, 1), or is set together with ``model.tag_free`` (a
        tag-free network has no tag to drop).
    """
    p = require_fraction("model.tag_dropout", cfg.model.get("tag_dropout", 0.0))
    if p > 0 and cfg.model.get("tag_free", False):
        raise ValueError(
            "model.tag_dropout drops a tag that model.tag_free never gives: set one of them"
        )
    return p


def identity_loss(cfg: DictConfig) -> float:
    """``model.identity_loss``, checked: the weight of the plant read-out's cross-entropy.

    Raises
    ------
    ValueError
        If it is not a finite number >= 0.
    """
    return require_nonnegative("model.identity_loss", cfg.model.get("identity_loss", 0.0))


def identity_noise(cfg: DictConfig) -> float:
    """``model.identity_noise``, checked: the largest std of the identifier's training noise.

    Raises
    ------
    ValueError
        If it is not a finite number >= 0, or is > 0 on a network without an identifier
        (``model.control_history`` or ``model.transition_identifier``).
    """
    std = require_nonnegative("model.identity_noise", cfg.model.get("identity_noise", 0.0))
    if std > 0 and not cfg.model.get("control_history", False):
        raise ValueError(
            "model.identity_noise perturbs what the identifier reads, and the network has "
            "none: set model.control_history=true (and model.transition_identifier), or "
            "identity_noise to 0"
        )
    return std


def identity_clean_fit(cfg: DictConfig) -> bool:
    """``model.identity_noise_clean_fit``, checked: fit the one-step models to clean windows.

    Raises
    ------
    ValueError
        If it is on without ``model.identity_noise`` > 0 or without
        ``model.transition_models``: there is no noise to keep out of no models.
    """
    on = bool(cfg.model.get("identity_noise_clean_fit", False))
    if on and not (identity_noise(cfg) > 0 and cfg.model.get("transition_models", False)):
        raise ValueError(
            "model.identity_noise_clean_fit keeps the identifier's training noise out of the "
            "one-step models' fit: it needs model.identity_noise > 0 and "
            "model.transition_models=true, or set it to false"
        )
    return on


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


def plant_versions(
    plants: list[Plant], manifest: dict[str, Any], per_plant: int | None = None
) -> list[tuple[str, Plant]]:
    """Each plant and, with variant data, its kept variants, labelled ``<plant>/v<index>``.

    The variants are rebuilt from the factors the data's manifest records
    (:func:`~generalist_control.plants.variants.make_variant`: the very plants the data stage
    simulated). ``per_plant`` keeps each plant's first that many variants (None: all).
    """
    recorded = manifest.get("variants") or {}
    out: list[tuple[str, Plant]] = []
    for p in plants:
        kept = recorded.get(p.name, {}).get("kept", [])
        out.append((p.name, p))
        out.extend(
            (f"{p.name}/v{v['index']}", make_variant(p, v["factors"])) for v in kept[:per_plant]
        )
    return out


def dagger_plants(plants: list[Plant], manifest: dict[str, Any]) -> list[Plant]:
    """The plants DAgger rolls out on: ``plants`` and, with variant data, their variants.

    With variant data the policy must also recover on the variants it imitates, so each
    training plant's kept variants join the rollouts (:func:`plant_versions`); each is
    labelled by its own LQI expert. ``dagger.rollouts`` is per plant, variants included.
    """
    return [q for _, q in plant_versions(plants, manifest)]


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
    block = cfg.data.get("variants") or {}  # fresh variants: the data's range and tries
    kwargs.setdefault("variant_range", float(block.get("range", DEFAULT_RANGE)))
    kwargs.setdefault("variant_tries", int(block.get("max_tries", 10)))
    if cfg.model.get("integral", False) and kwargs.get("takeover") == "bumpless":
        raise ValueError(
            "model.integral=true: DAgger must label from the integrator the policy sees; "
            "set dagger.takeover=tracked (or auto)"
        )
    return DAggerCallback(plants, **kwargs)


def closed_loop_validation(
    cfg: DictConfig, plants: list[Plant], manifest: dict[str, Any] | None = None
) -> L.Callback | None:
    """``val/closed_loop`` on every training plant (``closed_loop_val``; None when off).

    Raises
    ------
    ValueError
        ``closed_loop_val.variants`` is not a non-negative integer, or is set on data without
        variants.

    Notes
    -----
    ``closed_loop_val.variants: k`` (default 0) adds each plant's first ``k`` training
    variants from the data's ``manifest`` (:func:`plant_versions`), each scored against its
    own LQI expert, so that the checkpoint choice sees the variants' closed loops too.
    """
    spec = cfg.get("closed_loop_val")
    if not spec or not spec.get("enabled", True):
        return None
    per_plant = require_int("closed_loop_val.variants", spec.get("variants", 0), minimum=0)
    if per_plant and not (manifest or {}).get("variants"):
        raise ValueError(
            f"closed_loop_val.variants={per_plant}, but the training data holds no plant "
            "variants; generate them with data.variants.enabled=true (experiment=variants) "
            "or set closed_loop_val.variants=0"
        )
    versions = plant_versions(plants, manifest or {}, per_plant)  # 0: the plants alone
    return ClosedLoopValidation(
        [q for _, q in versions],
        list(spec.amplitudes),
        float(spec.duration),
        labels=[label for label, _ in versions],
    )


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


def check_resume(ckpt_path: str, meta: dict[str, Any]) -> None:
    """Refuse to resume from a checkpoint trained on other data."""
    old = torch.load(ckpt_path, map_location="cpu", weights_only=True)["hyper_parameters"]
    old_hash = old.get("meta", {}).get("content_hash")
    if old_hash != meta["content_hash"]:
        raise ValueError(
            f"checkpoint {ckpt_path} was trained on data {old_hash}, but "
            f"{meta['data_dir']} holds {meta['content_hash']}; resume on the same data"
        )


def rest_penalty(cfg: DictConfig, plants: list[Plant], meta: dict[str, Any]) -> RestPenalty | None:
    """The rest-stability term of ``cfg.rest`` on ``plants`` (None: ``rest.weight`` is 0).

    Raises
    ------
    ValueError
        If the block has unknown keys, or the term is on for a policy without the error
        integral (``model.integral``), whose rest has no integral to hold it.
    """
    spec = as_dict(cfg.get("rest") or {})
    unknown = set(spec) - {"weight", "every", "per_step", "reference", "slack"}
    if unknown:
        raise ValueError(
            f"rest has unknown keys {sorted(unknown)}; it takes weight, every, per_step, "
            "reference and slack"
        )
    weight = require_nonnegative("rest.weight", spec.pop("weight", 0.0))
    if weight == 0:
        return None
    if not cfg.model.get("integral", False):
        raise ValueError(
            "rest.weight > 0 needs model.integral=true: the term holds the loop at the error "
            "integral where the policy's control keeps the plant at rest"
        )
    return RestPenalty(
        plants,
        meta["tags"],
        int(cfg.data.history),
        bool(cfg.model.get("control_history", False)),
        weight=weight,
        seed=int(cfg.seed or 0),
        **spec,
    )
