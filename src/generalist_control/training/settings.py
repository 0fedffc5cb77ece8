"""A training run's config, read once into typed sections before anything is logged.

:func:`read_training` checks every key a training reads (types, ranges, how sections fit
together) and returns a :class:`TrainingSettings`; each part of the run then receives its
own section (the data module its :class:`LoaderSettings`, DAgger its :class:`DaggerSettings`,
...). The network's config (``model``) is checked by building it
(:class:`~generalist_control.model.policy.Policy`), also before anything is logged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from generalist_control.common.schema import require_int
from generalist_control.common.settings import (
    SettingError,
    positive,
    read_section,
    unit_interval,
)

__all__ = [
    "INITS",
    "ActuatorSettings",
    "AdaptSettings",
    "ClosedLoopValSettings",
    "DaggerSettings",
    "LabellerSettings",
    "LoaderSettings",
    "SamplerSettings",
    "TrainingSettings",
    "VariantSettings",
    "model_config",
    "read_training",
]


@dataclass(frozen=True)
class LoaderSettings:
    """``loader``: the training data's split and batches."""

    val_fraction: float = 0.1  #: of each plant's trajectories, held out whole
    batch_size: int = 512
    val_batch_size: int = 8192

    def __post_init__(self) -> None:
        if not 0.0 <= self.val_fraction < 1.0:
            raise SettingError("val_fraction", f"must lie in [0, 1), got {self.val_fraction}")
        for name in ("batch_size", "val_batch_size"):
            if getattr(self, name) < 1:
                raise SettingError(name, f"must be a positive integer, got {getattr(self, name)}")


@dataclass(frozen=True)
class ActuatorSettings:
    """``dagger.sampler.actuator``: a random actuator per rollout row (``training/actuator``)."""

    lag: float = 0.0  #: largest first-order time constant, in sample periods
    offset: float = 0.0  #: largest constant offset, times the plant's control scale

    def __post_init__(self) -> None:
        positive("lag", self.lag, strict=False)
        positive("offset", self.offset, strict=False)


@dataclass(frozen=True)
class VariantSettings:
    """``dagger.sampler.variants``: plant variants in the rollouts."""

    data: int | None = None  #: the data's variants per plant and round, in turn; null: all
    fresh: int = 0  #: variants per plant drawn fresh each round (fit for LQI)
    seed: int = 3001  #: seed of round 0's fresh draw (round i: seed + i)

    def __post_init__(self) -> None:
        for name in ("data", "fresh", "seed"):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise SettingError(name, f"must be a non-negative integer, got {value}")


@dataclass(frozen=True)
class SamplerSettings:
    """``dagger.sampler``: which rollouts a DAgger round runs (:mod:`.sampler`)."""

    rollouts: int = 8  #: step rollouts from rest per plant version and round
    duration: float = 10.0  #: seconds per rollout
    families: int = 1  #: rollouts of each of the data's families per plant and round
    noise: float = 0.0  #: std of white noise on the executed control, x the control scale
    actuator: ActuatorSettings | None = None
    variants: VariantSettings | None = None

    def __post_init__(self) -> None:
        for name in ("rollouts", "families"):
            if getattr(self, name) < 0:
                raise SettingError(
                    name, f"must be a non-negative integer, got {getattr(self, name)}"
                )
        positive("duration", self.duration)
        positive("noise", self.noise, strict=False)


@dataclass(frozen=True)
class LabellerSettings:
    """``dagger.labeller``: which visited windows the experts label (:mod:`.labeller`)."""

    bound_factor: float = 3.0  #: cut rollouts beyond this times the data's largest state

    def __post_init__(self) -> None:
        positive("bound_factor", self.bound_factor)


@dataclass(frozen=True)
class DaggerSettings:
    """``dagger``: when the rounds run and how much the expert steers (:mod:`.dagger`)."""

    start_epoch: int = 6  #: first round after this many epochs
    every: int = 4  #: then every this many epochs
    rounds: int = 5
    beta: float = 0.5  #: the expert's share of the executed control in round 0 ...
    beta_decay: float = 0.5  #: ... times this per round
    sampler: SamplerSettings = field(default_factory=SamplerSettings)
    labeller: LabellerSettings = field(default_factory=LabellerSettings)

    def __post_init__(self) -> None:
        for name in ("start_epoch", "every", "rounds"):
            if getattr(self, name) < (0 if name == "start_epoch" else 1):
                raise SettingError(name, f"is out of range: {getattr(self, name)}")
        unit_interval("beta", self.beta)
        unit_interval("beta_decay", self.beta_decay)

    def beta_at(self, round_index: int) -> float:
        """The expert's share in round ``round_index`` (0-based): ``beta * beta_decay ** i``."""
        return self.beta * self.beta_decay**round_index


@dataclass(frozen=True)
class ClosedLoopValSettings:
    """``closed_loop_val``: the closed-loop score after every validation epoch."""

    amplitudes: tuple[float, ...] = (1.0, -3.0)  #: steps from rest, x amplitude_scale
    duration: float = 10.0

    def __post_init__(self) -> None:
        if not self.amplitudes:
            raise SettingError("amplitudes", "must name at least one step")
        positive("duration", self.duration)


#: Where a new plant's row starts (``adapt.init``).
INITS = ("nearest", "mean")


@dataclass(frozen=True)
class AdaptSettings:
    """``adapt``: how a new plant's row is learned (``python -m generalist_control.adapt``)."""

    learn: bool = True  #: false: name the plant only (its scales and start row)
    init: str = "nearest"  #: the row's start: nearest (a trained row) or mean
    epochs: int = 20  #: passes over the windows, first and after each round
    lr: float = 1.0e-2
    batch_size: int = 512
    rounds: int = 3  #: DAgger rounds on the plant (generated demonstrations only)
    beta: float = 0.5  #: the expert's share in round 0 ...
    beta_decay: float = 0.5  #: ... times this per round
    unfreeze: tuple[str, ...] = ()  #: parameters learned beside the row, by name prefix

    def __post_init__(self) -> None:
        if self.init not in INITS:
            raise SettingError("init", f"must be one of {list(INITS)}, got {self.init!r}")
        for name in ("epochs", "rounds"):
            if getattr(self, name) < 0:
                raise SettingError(name, f"must be >= 0, got {getattr(self, name)}")
        if self.batch_size < 1:
            raise SettingError("batch_size", f"must be >= 1, got {self.batch_size}")
        positive("lr", self.lr)
        unit_interval("beta", self.beta)
        unit_interval("beta_decay", self.beta_decay)

    def beta_at(self, round_index: int) -> float:
        """The expert's share in round ``round_index`` (0-based)."""
        return self.beta * self.beta_decay**round_index


@dataclass(frozen=True)
class TrainingSettings:
    """Every section a training reads, checked (:func:`read_training`)."""

    seed: int
    threads: int
    max_epochs: int
    monitor: str
    history: int
    horizon: int
    model: dict[str, Any]
    optimizer: dict[str, Any]
    scheduler: dict[str, Any] | None
    loader: LoaderSettings
    dagger: DaggerSettings | None
    closed_loop_val: ClosedLoopValSettings | None


def _plain(cfg: DictConfig, key: str) -> Any:
    """``cfg[key]`` resolved to plain types (None when absent or null)."""
    node = OmegaConf.select(cfg, key)
    if node is None:
        return None
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


def _optimizer(spec: Any, scheduler: Any, max_epochs: int) -> tuple[dict, dict | None]:
    """The optimiser and scheduler partials, tried on one parameter (lr < 0 fails here)."""
    if not isinstance(spec, dict) or "_target_" not in spec:
        raise ValueError("optimizer must name an optimiser (_target_, _partial_: true)")
    if isinstance(scheduler, dict) and scheduler.get("T_max", 0) is None:
        scheduler = {**scheduler, "T_max": max_epochs}  # cosine over the whole run
    try:
        optimizer = instantiate(spec)(params=[torch.nn.Parameter(torch.zeros(1))])
        if scheduler:
            instantiate(scheduler)(optimizer=optimizer)
    except Exception as exc:
        cause = exc.__cause__ or exc
        raise ValueError(f"optimizer/scheduler refused: {cause}") from None
    return spec, scheduler


def model_config(cfg: DictConfig) -> dict[str, Any]:
    """The network's config: ``model`` with ``experts`` and the data's window sizes.

    ``experts`` is a top-level key (``experts=5`` works as typed); ``history`` and
    ``horizon`` come from the data config, so the network always matches its windows.
    """
    model = _plain(cfg, "model")
    if not isinstance(model, dict):
        raise ValueError("model must be a network config (conf/model)")
    keys = {"experts": "experts", "history": "data.history", "horizon": "data.horizon"}
    return {**model, **{k: _plain(cfg, key) for k, key in keys.items()}}


def read_training(cfg: DictConfig) -> TrainingSettings:
    """The training config ``cfg`` (``conf/config.yaml`` composed), checked and typed.

    Raises
    ------
    ValueError
        Naming the key: a value of the wrong type or out of range (``trainer.max_epochs``
        must be >= 1, ``threads`` >= 1, ...), an unknown key in a section, an optimiser
        that refuses its settings, or sections that do not fit together (``monitor:
        val/closed_loop`` without ``closed_loop_val``).
    """
    max_epochs = require_int("trainer.max_epochs", _plain(cfg, "trainer.max_epochs"))
    monitor = _plain(cfg, "monitor")
    if monitor not in ("val/loss", "val/closed_loop"):
        raise ValueError(f"monitor must be val/loss or val/closed_loop, got {monitor!r}")
    closed = _plain(cfg, "closed_loop_val")
    if monitor == "val/closed_loop" and closed is None:
        raise ValueError(
            "monitor=val/closed_loop needs the closed-loop validation, which closed_loop_val="
            "null turns off: set monitor=val/loss, or keep closed_loop_val"
        )
    dagger = _plain(cfg, "dagger")
    optimizer, scheduler = _optimizer(
        _plain(cfg, "optimizer"), _plain(cfg, "scheduler"), max_epochs
    )
    history = require_int("data.history", _plain(cfg, "data.history"))
    horizon = require_int("data.horizon", _plain(cfg, "data.horizon"))
    return TrainingSettings(
        seed=require_int("seed", _plain(cfg, "seed"), minimum=0),
        threads=require_int("threads", _plain(cfg, "threads")),
        max_epochs=max_epochs,
        monitor=str(monitor),
        history=history,
        horizon=horizon,
        model=model_config(cfg),
        optimizer=optimizer,
        scheduler=scheduler,
        loader=read_section(LoaderSettings, _plain(cfg, "loader"), "loader"),
        dagger=None if dagger is None else read_section(DaggerSettings, dagger, "dagger"),
        closed_loop_val=(
            None
            if closed is None
            else read_section(ClosedLoopValSettings, closed, "closed_loop_val")
        ),
    )
