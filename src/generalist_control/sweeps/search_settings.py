"""The Optuna search's settings (``conf/hparams_search/``), read once by ``tune.py``.

Every default lives in the YAML; a search file of one's own must set every field.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from generalist_control.common.settings import SettingError, positive

__all__ = ["HeartbeatSettings", "PLAIN_NAME", "SearchSettings"]

#: A study name: also a folder name (no separator, no ``..``) and an MLflow filter value.
PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


@dataclass(frozen=True)
class HeartbeatSettings:
    """Dead workers: a ``RUNNING`` trial silent for ``grace_period`` s is failed, maybe retried.

    ``interval`` null turns the heartbeat (and the failing of dead workers' trials) off.
    """

    interval: int | None
    grace_period: int | None
    max_retry: int

    def __post_init__(self) -> None:
        for name in ("interval", "grace_period"):
            value = getattr(self, name)
            if value is not None:
                positive(name, value)
        positive("max_retry", self.max_retry, strict=False)


@dataclass(frozen=True)
class SearchSettings:
    """``hparams_search``: the study, its trial budget, sampler, pruner and search space.

    ``sampler`` and ``pruner`` are ``_target_`` mappings of ``optuna.samplers`` and
    ``optuna.pruners`` classes (null: Optuna's default sampler, no pruning); ``params`` is
    the search space's tree (:func:`~generalist_control.sweeps.search_space.parse_space`).
    """

    study_name: str
    storage: str
    direction: str
    metric: str
    monitor: str
    n_trials: int
    max_trials: int | None
    timeout: float | None
    worker: int
    trials_dir: str | None
    progress_bar: bool
    allow_config_change: bool
    identity_keys: tuple[str, ...]
    sampler: Any | None  # a _target_ mapping
    pruner: Any | None
    heartbeat: HeartbeatSettings
    params: Any

    def __post_init__(self) -> None:
        if not PLAIN_NAME.fullmatch(self.study_name):
            raise SettingError(
                "study_name",
                f"= {self.study_name!r} is not a plain name: it also names the folder of the "
                "study's trials (<trials_dir>/<study_name>), which must stay in trials_dir; "
                "use letters, digits, '.', '_' and '-', starting with a letter or digit, "
                "e.g. generalist-control-v2",
            )
        if self.direction not in ("minimize", "maximize"):
            raise SettingError("direction", f"must be minimize or maximize: {self.direction!r}")
        positive("n_trials", self.n_trials, strict=False)
        if self.max_trials is not None:
            positive("max_trials", self.max_trials, strict=False)
        if self.timeout is not None:
            positive("timeout", self.timeout)
