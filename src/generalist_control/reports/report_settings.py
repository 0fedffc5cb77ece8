"""The ablation report's config (``conf/report``), read once by ``report.py``.

Every key is described in ``conf/report/default.yaml``, its one default.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

__all__ = ["Baseline", "GateSettings", "ReportJob", "ReportSettings", "Tolerance"]


@dataclass(frozen=True)
class Baseline:
    """``report.baseline``: the d of the M sweep and the M of the d sweep."""

    hidden: int
    experts: int


@dataclass(frozen=True)
class GateSettings:
    """``report.gate``: the model whose gate weights are drawn, and how they are measured."""

    experts: int
    plants: tuple[str, ...] | None
    duration: float


@dataclass(frozen=True)
class Tolerance:
    """``report.claims``: how close to the paper's figure a claim's figure must be."""

    factor: float
    count_relative: float
    share_points: float


@dataclass(frozen=True)
class ReportSettings:
    """``report``: which runs, which figures, where to."""

    experiment_name: str | None
    parent_run: tuple[str, ...] | None
    filter_string: str
    allow_mixed: bool
    identity_keys: tuple[str, ...]
    baseline: Baseline
    hidden: tuple[int, ...]
    experts: tuple[int, ...]
    plants: tuple[str, ...] | None
    gate: GateSettings
    evaluations_dir: str | None
    recipe: str | None
    claims: Tolerance
    out_dir: str
    log_mlflow: bool
    run_name: str


@dataclass(frozen=True)
class ReportJob:
    """The report's settings; ``plants``: ``report.plants``, else ``closed_loop.systems``."""

    report: ReportSettings
    logger: Mapping[str, Any]
    plants: tuple[str, ...]
    bar: Mapping[str, Any]
    threads: int
