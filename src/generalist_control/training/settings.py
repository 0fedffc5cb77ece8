"""A training run's config, read once into typed settings before anything is logged.

Entry points call :func:`read_training`; each part receives its own section. Every default
lives in ``conf/``, none here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import torch
from hydra.utils import instantiate

from generalist_control.common.paths import stage_dir
from generalist_control.common.secrets import redact
from generalist_control.common.sections import (
    SettingError,
    at_least,
    positive,
    read_section,
    require_int,
    unit_interval,
)
from generalist_control.data.generation import enabled_families
from generalist_control.plants.catalog import plants_from_config
from generalist_control.plants.definition import Plant
from generalist_control.plants.variants import variant_range

__all__ = [
    "ActuatorSettings",
    "ClosedLoopSettings",
    "ClosedLoopValSettings",
    "DaggerSettings",
    "FamilyTraining",
    "LabellerSettings",
    "LoaderSettings",
    "RolloutData",
    "SamplerSettings",
    "TrainingSettings",
    "VariantSettings",
    "read_training",
    "rollout_data",
]


T = TypeVar("T")


@dataclass(frozen=True)
class LoaderSettings:
    """``loader``: the training data's split and batches."""

    val_fraction: float  #: of each plant's trajectories, held out whole
    batch_size: int
    val_batch_size: int

    def __post_init__(self) -> None:
        if not 0.0 <= self.val_fraction < 1.0:
            raise SettingError("val_fraction", f"must lie in [0, 1), got {self.val_fraction}")
        at_least(1, self, "batch_size", "val_batch_size")


@dataclass(frozen=True)
class ActuatorSettings:
    """``dagger.sampler.actuator``: a random actuator per rollout row (``training/actuator``)."""

    lag: float  #: largest first-order time constant, in sample periods
    offset: float  #: largest constant offset, times the plant's control scale

    def __post_init__(self) -> None:
        positive("lag", self.lag, strict=False)
        positive("offset", self.offset, strict=False)


@dataclass(frozen=True)
class VariantSettings:
    """``dagger.sampler.variants``: plant variants in the rollouts."""

    data: int | None  #: the data's variants per plant and round, in turn; null: all
    fresh: int  #: variants per plant drawn fresh each round (fit for LQI)
    seed: int  #: seed of round 0's fresh draw (round i: seed + i)

    def __post_init__(self) -> None:
        at_least(0, self, "data", "fresh", "seed")


@dataclass(frozen=True)
class SamplerSettings:
    """``dagger.sampler``: which rollouts a DAgger round runs (:mod:`.sampler`)."""

    rollouts: int  #: step rollouts from rest per plant version and round
    duration: float  #: seconds per rollout
    families: int  #: rollouts of each of the data's families per plant and round
    noise: float  #: std of white noise on the executed control, x the control scale
    actuator: ActuatorSettings | None
    variants: VariantSettings | None

    def __post_init__(self) -> None:
        at_least(0, self, "rollouts", "families")
        positive("duration", self.duration)
        positive("noise", self.noise, strict=False)


@dataclass(frozen=True)
class LabellerSettings:
    """``dagger.labeller``: which visited windows the experts label (:mod:`.labeller`)."""

    bound_factor: float  #: cut rollouts beyond this times the data's largest state

    def __post_init__(self) -> None:
        positive("bound_factor", self.bound_factor)


@dataclass(frozen=True)
class DaggerSettings:
    """``dagger``: when the rounds run and how much the expert steers (:mod:`.dagger`)."""

    start_epoch: int  #: first round after this many epochs
    every: int  #: then every this many epochs
    rounds: int
    beta: float  #: the expert's share of the executed control in round 0 ...
    beta_decay: float  #: ... times this per round
    sampler: SamplerSettings
    labeller: LabellerSettings

    def __post_init__(self) -> None:
        at_least(0, self, "start_epoch")
        at_least(1, self, "every", "rounds")
        unit_interval("beta", self.beta)
        unit_interval("beta_decay", self.beta_decay)

    def beta_at(self, round_index: int) -> float:
        """The expert's share in round ``round_index`` (0-based): ``beta * beta_decay ** i``."""
        return self.beta * self.beta_decay**round_index


@dataclass(frozen=True)
class ClosedLoopValSettings:
    """``closed_loop_val``: the closed-loop score after every validation epoch."""

    amplitudes: tuple[float, ...]  #: steps from rest, x amplitude_scale
    duration: float

    def __post_init__(self) -> None:
        if not self.amplitudes:
            raise SettingError("amplitudes", "must name at least one step")
        positive("duration", self.duration)


@dataclass(frozen=True)
class ClosedLoopSettings:
    """``closed_loop``: the ablation's closed-loop score after training (Section 7)."""

    systems: tuple[str, ...]  #: the plants scored; () turns it off
    duration: float

    def __post_init__(self) -> None:
        positive("duration", self.duration)


@dataclass(frozen=True)
class FamilyTraining:
    """``train_families``: the families trained on and how much of them each check sees."""

    dirs: tuple[str, ...]  #: the families' data folders (``generate_families``' data_dir)
    dagger_plants: int  #: family plants rolled out per DAgger round, in turn
    closed_loop_plants: int  #: the first family plants in the closed-loop validation
    #: a family group (``conf/families``) at a seed no training uses: its plants join the
    #: closed-loop validation zero-shot (:mod:`.unseen_draw`); None: none
    validation: Any | None = None
    #: which family plants each DAgger round rolls out (``_target_``: ``training.sampler``'s
    #: ``InTurn``, ``WorstFirst``); None: in turn
    dagger_pick: Any | None = None

    def __post_init__(self) -> None:
        if not self.dirs:
            raise SettingError("dirs", "must name at least one family's data folder")
        for name in ("dagger_plants", "closed_loop_plants"):
            if getattr(self, name) < 0:
                raise SettingError(name, f"must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class RolloutData:
    """What DAgger's rollouts take from the data recipe (``data``)."""

    amplitude_limit: float  #: ``data.amplitudes.limit``
    families: dict[str, dict[str, Any]]  #: the enabled ``data.families``
    variant_range: float  #: ``data.variants.range``: fresh variants' half-width
    variant_tries: int  #: ``data.variants.max_tries``
    #: the whole recipe: demonstrations of plants made in training
    recipe: dict[str, Any] = field(default_factory=dict)


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
    closed_loop: ClosedLoopSettings
    families: FamilyTraining | None  #: ``train_families``: null, the catalogue alone
    rollout_data: RolloutData
    plants: tuple[Plant, ...]  #: the set's plants (``systems``), by tag
    held_out: tuple[str, ...]  #: plants of the set training never sees
    data_dir: Path
    run_dir: Path  #: checkpoints (``run_dir``, else Hydra's output folder)
    models_dir: Path  #: where ``policy.ckpt`` and ``metrics.json`` go
    ckpt_path: str | None  #: the Lightning checkpoint to resume from
    trainer: dict[str, Any]  #: ``trainer`` (Lightning's Trainer, instantiated by training)
    callbacks: tuple[dict[str, Any], ...]  #: ``callbacks``: each a node with a _target_
    logger: dict[str, Any]  #: ``logger``: where and how the run is logged
    resolved: dict[str, Any]  #: the whole config, resolved and redacted (the run's record)

    @property
    def trained_names(self) -> list[str]:
        """The set's plants less :attr:`held_out`: those the data module keeps."""
        return [p.name for p in self.plants if p.name not in self.held_out]


def _optimizer(spec: Any, scheduler: Any, max_epochs: int) -> tuple[dict, dict | None]:
    """The optimiser and scheduler partials, tried on one parameter (lr < 0 fails here)."""
    if not isinstance(spec, dict) or "_target_" not in spec:
        raise ValueError("optimizer must name an optimiser (_target_, _partial_: true)")
    if isinstance(scheduler, dict) and "T_max" in scheduler and scheduler["T_max"] is None:
        scheduler = {**scheduler, "T_max": max_epochs}  # cosine over the whole run
    try:
        optimizer = instantiate(spec)(params=[torch.nn.Parameter(torch.zeros(1))])
        if scheduler:
            instantiate(scheduler)(optimizer=optimizer)
    except Exception as exc:
        cause = exc.__cause__ or exc
        raise ValueError(f"optimizer/scheduler refused: {cause}") from None
    return spec, scheduler


def _held_out(config: Mapping[str, Any], plants: list[Plant]) -> tuple[str, ...]:
    """``held_out``: plants of the set training never sees (the held-out protocol)."""
    names = [p.name for p in plants]
    held = tuple(str(h) for h in config["held_out"] or ())
    unknown = [h for h in held if h not in names]
    if unknown:
        raise ValueError(
            f"held_out names {unknown}, which the plant set (systems) does not hold; it holds "
            f"{names}"
        )
    if not set(names) - set(held):
        raise ValueError(f"held_out={list(held)} leaves no plant of the set to train on")
    return held


def _models_dir(config: Mapping[str, Any], run_dir: Path) -> Path:
    """Where the run writes ``policy.ckpt`` and ``metrics.json``.

    ``paths.published_dir`` only when it publishes (``publish=true``: the DVC stage); else
    ``paths.models_dir`` if that is another folder (an Optuna trial's), else ``<run_dir>/models``.
    """
    published = config["paths"]["published_dir"]
    models_dir = Path(str(config["paths"]["models_dir"]))
    if config["publish"]:
        return Path(published) if published else models_dir
    if published is None or models_dir.resolve() != Path(published).resolve():
        return models_dir
    return run_dir / "models"


def rollout_data(data: Mapping[str, Any]) -> RolloutData:
    """What DAgger's rollouts take from the data recipe ``data`` (plain types)."""
    variants = data["variants"]
    return RolloutData(
        amplitude_limit=float(data["amplitudes"]["limit"]),
        families=enabled_families(data),
        variant_range=variant_range(variants["range"], "data.variants.range"),
        variant_tries=require_int("data.variants.max_tries", variants["max_tries"]),
        recipe=dict(data),
    )


def _optional(cls: type[T], config: Mapping[str, Any], key: str) -> T | None:
    """Section ``key`` of ``config`` read as ``cls``; None where it is null (switched off)."""
    return None if config[key] is None else read_section(cls, config[key], key)


def _callbacks(config: Mapping[str, Any], run_dir: Path) -> tuple[dict[str, Any], ...]:
    """The ``callbacks`` nodes that name a class (a null one is switched off).

    ``dirpath: null`` becomes ``<run_dir>/checkpoints``.
    """
    nodes = (config["callbacks"] or {}).values()
    checkpoints = {"dirpath": str(run_dir / "checkpoints")}
    return tuple(
        {**n, **checkpoints} if "dirpath" in n and n["dirpath"] is None else n
        for n in nodes
        if isinstance(n, dict) and "_target_" in n
    )


def read_training(config: Mapping[str, Any]) -> TrainingSettings:
    """The training config ``config`` (``conf/config.yaml`` composed, as plain types), checked.

    Raises
    ------
    ValueError
        Naming the key: a wrong type or range, an unknown key, an optimiser that refuses its
        settings, sections that do not fit together, a plant the set does not hold.
    """
    max_epochs = require_int("trainer.max_epochs", config["trainer"]["max_epochs"])
    monitor = config["monitor"]
    if monitor not in ("val/loss", "val/closed_loop"):
        raise ValueError(f"monitor must be val/loss or val/closed_loop, got {monitor!r}")
    if not isinstance(config["model"], dict):
        raise ValueError("model must be a network config (conf/model)")
    if monitor == "val/closed_loop" and config["closed_loop_val"] is None:
        raise ValueError(
            "monitor=val/closed_loop needs the closed-loop validation, which closed_loop_val="
            "null turns off: set monitor=val/loss, or keep closed_loop_val"
        )
    optimizer, scheduler = _optimizer(config["optimizer"], config["scheduler"], max_epochs)
    plants = plants_from_config(config["systems"])
    run_dir = Path(str(config["run_dir"])) if config["run_dir"] else stage_dir("train")
    return TrainingSettings(
        seed=require_int("seed", config["seed"], minimum=0),
        threads=require_int("threads", config["threads"]),
        max_epochs=max_epochs,
        monitor=str(monitor),
        history=require_int("data.history", config["data"]["history"]),
        horizon=require_int("data.horizon", config["data"]["horizon"]),
        model=config["model"],
        optimizer=optimizer,
        scheduler=scheduler,
        loader=read_section(LoaderSettings, config["loader"], "loader"),
        dagger=_optional(DaggerSettings, config, "dagger"),
        closed_loop_val=_optional(ClosedLoopValSettings, config, "closed_loop_val"),
        closed_loop=read_section(ClosedLoopSettings, config["closed_loop"], "closed_loop"),
        families=_optional(FamilyTraining, config, "train_families"),
        rollout_data=rollout_data(config["data"]),
        plants=tuple(plants),
        held_out=_held_out(config, plants),
        data_dir=Path(str(config["paths"]["data_dir"])),
        run_dir=run_dir,
        models_dir=_models_dir(config, run_dir),
        ckpt_path=config["ckpt_path"] or None,
        trainer=config["trainer"],
        callbacks=_callbacks(config, run_dir),
        logger=config["logger"],
        resolved=redact(dict(config)),
    )
