"""The ``evaluation`` config group read once into typed settings (:func:`read_evaluation`).

The entry point reads it; every part below gets its own section. Defaults live in
``conf/evaluation/default.yaml`` only: a key missing there is an error, not a guess.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from generalist_control.common.sections import SettingError, positive, read_section
from generalist_control.deploy.export import BACKENDS

__all__ = [
    "CrazyflieSettings",
    "EvaluationSettings",
    "QualityBar",
    "SetpointSettings",
    "VariantBar",
    "VariantEvalSettings",
    "VariantValidation",
    "read_evaluation",
]


@dataclass(frozen=True)
class SetpointSettings:
    """``evaluation.setpoint``: a ``hold``-s step of ``reference``, its last ``tail`` s judged."""

    reference: float
    hold: float
    tail: float

    def __post_init__(self) -> None:
        if not 0.0 < self.tail < self.hold:
            raise SettingError("tail", f"must lie in (0, hold = {self.hold}), got {self.tail}")


@dataclass(frozen=True)
class QualityBar:
    """``evaluation.quality_bar``: GC against LQI (:mod:`~.summary`)."""

    ISE_ratio: float
    ITAE_ratio: float
    relative_ess: float
    RMSE_ratio: float
    anti_windup: tuple[str, ...]
    anti_windup_tolerance: float

    def __post_init__(self) -> None:
        for name in ("ISE_ratio", "ITAE_ratio", "relative_ess", "RMSE_ratio"):
            positive(name, getattr(self, name))
        positive("anti_windup_tolerance", self.anti_windup_tolerance, strict=False)


@dataclass(frozen=True)
class CrazyflieSettings:
    """``evaluation.crazyflie``: the sim-to-real stand-in's flights."""

    amplitude: float
    duration: float
    runs: int
    seed: int

    def __post_init__(self) -> None:
        positive("duration", self.duration)
        if self.runs < 1:
            raise SettingError("runs", f"must be at least 1, got {self.runs}")


@dataclass(frozen=True)
class VariantBar:
    """``evaluation.variants.bar`` (:mod:`~.variant_summary`)."""

    median_ISE_ratio: float
    worst_ISE_ratio: float
    nominal_worse: float
    min_variants: int


@dataclass(frozen=True)
class VariantValidation:
    """``evaluation.variants.validation``: the held-out draw."""

    seed: int
    count: int

    def __post_init__(self) -> None:
        if self.count < 5:
            raise SettingError("count", f"must be at least 5 (the bar needs 5), got {self.count}")


@dataclass(frozen=True)
class VariantEvalSettings:
    """``evaluation.variants``: unseen plant variants (:mod:`~.variant_eval`)."""

    enabled: bool
    count: int
    range: float
    seed: int
    max_tries: int
    scenarios: tuple[str, ...]
    bar: VariantBar
    validation: VariantValidation | None

    def __post_init__(self) -> None:
        if self.count < 5:
            raise SettingError("count", f"must be at least 5 (the bar needs 5), got {self.count}")
        if not 0.0 < self.range < 1.0:
            raise SettingError("range", f"must lie in (0, 1), got {self.range}")
        if self.max_tries < 1:
            raise SettingError("max_tries", f"must be at least 1, got {self.max_tries}")
        if not self.scenarios:
            raise SettingError("scenarios", "must name at least one scenario")
        if self.validation is not None and self.validation.seed == self.seed:
            raise SettingError(
                "validation.seed",
                f"= {self.seed} is the test variants' seed: choose another, so the held-out "
                "check draws other variants",
            )


@dataclass(frozen=True)
class EvaluationSettings:
    """The ``evaluation`` group (``conf/evaluation/default.yaml`` says what each key means)."""

    scenarios: Any  #: name -> its spec (:mod:`generalist_control.simulation.scenarios`)
    setpoint: SetpointSettings | None
    quality_bar: QualityBar
    crazyflie: CrazyflieSettings | None
    backend: str
    mlflow_prefix: str
    plots: bool
    variants: VariantEvalSettings

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise SettingError("backend", f"must be one of {list(BACKENDS)}, got {self.backend!r}")
        if not self.mlflow_prefix:
            raise SettingError("mlflow_prefix", "must not be empty")
        if not isinstance(self.scenarios, dict):
            raise SettingError("scenarios", f"must be a mapping, got {self.scenarios!r}")
        bad = [n for n, s in self.scenarios.items() if not isinstance(s, dict) or "kind" not in s]
        if bad:
            raise SettingError("scenarios", f"{bad}: each scenario is a mapping with a kind")
        missing = [n for n in self.variants.scenarios if n not in self.scenarios]
        if missing:
            raise SettingError("variants.scenarios", f"names {missing}, not in scenarios")


def read_evaluation(node: Any) -> EvaluationSettings:
    """``evaluation`` (a plain mapping: :func:`~generalist_control.common.sections.as_dict`).

    Raises
    ------
    ValueError
        Naming the key: unknown, missing, of another type or out of range.
    """
    return read_section(EvaluationSettings, node, "evaluation")
