"""The adapt command's config (``conf/adapt.yaml``), read once into typed settings."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from generalist_control.common.sections import (
    SettingError,
    at_least,
    positive,
    read_section,
    require_int,
    unit_interval,
)
from generalist_control.model.policy import POLICY_FILE
from generalist_control.training.settings import ClosedLoopValSettings, DaggerSettings

__all__ = ["INITS", "AdaptRequest", "AdaptSettings", "read_request"]

#: Where a new plant's row starts (``adapt.init``).
INITS = ("nearest", "mean")


@dataclass(frozen=True)
class AdaptSettings:
    """``adapt``: how the new plant's row is learned."""

    learn: bool  #: false: name the plant only (its scales and start row)
    init: str  #: the row's start: nearest (a trained row, or their mean) or mean
    epochs: int  #: passes over the windows, first and after each round
    lr: float
    batch_size: int
    rounds: int  #: DAgger rounds on the plant (generated demonstrations only)
    beta: float  #: the expert's share in round 0 ...
    beta_decay: float  #: ... times this per round
    unfreeze: tuple[str, ...]  #: parameters learned beside the row, by name prefix

    def __post_init__(self) -> None:
        if self.init not in INITS:
            raise SettingError("init", f"must be one of {list(INITS)}, got {self.init!r}")
        at_least(0, self, "epochs", "rounds")
        at_least(1, self, "batch_size")
        positive("lr", self.lr)
        unit_interval("beta", self.beta)
        unit_interval("beta_decay", self.beta_decay)

    def beta_at(self, round_index: int) -> float:
        """The expert's share in round ``round_index`` (0-based)."""
        return self.beta * self.beta_decay**round_index


@dataclass(frozen=True)
class AdaptRequest:
    """Everything the adapt command reads, checked (:func:`read_request`)."""

    plant: str  #: a catalogue name or the path of a plant YAML
    policy: str  #: the base policy: a path or an MLflow URI
    demos: str | None  #: recorded demonstrations; None: the plant's LQI
    run_dir: Path  #: the run folder the command writes
    seed: int
    threads: int
    adapt: AdaptSettings
    dagger: DaggerSettings | None  #: the sampler and labeller of the rounds
    scoring: ClosedLoopValSettings  #: ``closed_loop_val``: the score that picks the row kept
    data: Mapping[str, Any]  #: the data stage's recipe, for the plant's demonstrations
    logger: Mapping[str, Any]
    listed: tuple[str, ...]  #: the plants of ``systems`` (the evaluate command adds others)


def read_request(config: Mapping[str, Any], run_dir: Path) -> AdaptRequest:
    """The adapt command's settings, checked and typed.

    ``config`` is the whole of ``conf/adapt.yaml`` composed and resolved to plain types (not a
    ``DictConfig``); ``run_dir`` the run folder the command writes.

    Raises
    ------
    ValueError
        Naming the key: no ``plant``, a bad ``adapt`` setting, ``closed_loop_val=null``,
        DAgger rounds with ``dagger=null``.
    """
    if not config["plant"]:
        raise ValueError("plant= is required: a catalogue name or the path of a plant YAML")
    settings = read_section(AdaptSettings, config["adapt"], "adapt")
    if config["closed_loop_val"] is None:
        raise ValueError(
            "closed_loop_val=null: adapt scores each row's closed loop with it to keep the "
            "best; leave closed_loop_val as configured"
        )
    dagger = config["dagger"]
    if dagger is None and settings.learn and settings.rounds and not config["demos"]:
        raise ValueError(
            f"adapt.rounds={settings.rounds} needs DAgger's sampler and labeller, which "
            "dagger=null turns off: set adapt.rounds=0, or leave dagger as configured"
        )
    default_policy = Path(config["paths"]["models_dir"]) / POLICY_FILE
    return AdaptRequest(
        plant=str(config["plant"]),
        policy=str(config["policy"] or default_policy),
        demos=str(config["demos"]) if config["demos"] else None,
        run_dir=Path(run_dir),
        seed=require_int("seed", config["seed"], minimum=0),
        threads=require_int("threads", config["threads"]),
        adapt=settings,
        dagger=None if dagger is None else read_section(DaggerSettings, dagger, "dagger"),
        scoring=read_section(ClosedLoopValSettings, config["closed_loop_val"], "closed_loop_val"),
        data=config["data"],
        logger=config["logger"],
        listed=tuple(config["systems"]["plants"]),
    )
