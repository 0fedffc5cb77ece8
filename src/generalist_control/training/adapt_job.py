"""An adaptation's inputs, checked: what :func:`~.adapt.prepare` gives :func:`~.adapt.learn`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from generalist_control.data.windows import Windows
from generalist_control.model.policy import Policy
from generalist_control.training.labeller import ExpertLabeller
from generalist_control.training.newplant import NewPlant
from generalist_control.training.sampler import RolloutSampler
from generalist_control.training.settings import AdaptSettings, ClosedLoopValSettings

__all__ = ["AdaptJob"]


@dataclass(frozen=True)
class AdaptJob:
    """Everything an adaptation needs, checked (:func:`prepare`); nothing written yet."""

    settings: AdaptSettings
    new: NewPlant  #: the plant, on the policy's new row (or a free one, tag-free)
    policy: Policy  #: the base policy, as loaded
    meta: dict[str, Any]
    source: str  #: ``policy=`` as given
    path: Path  #: the base policy's local file
    windows: Windows
    demos: dict[str, Any]  #: where the windows came from, how many
    sampler: RolloutSampler | None  #: DAgger on the plant; None with recorded demonstrations
    labeller: ExpertLabeller
    scoring: ClosedLoopValSettings  #: the closed-loop score that picks the row kept
    seed: int
    run_dir: Path
