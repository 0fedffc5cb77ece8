"""The Optuna search's settings (``conf/hparams_search/``) and its space, read once by ``tune.py``.

Every default lives in the YAML. A study's score ranks trials only while everything but the
searched keys stays the same: its fixed config is recorded at creation, checked on resume.
"""

from __future__ import annotations

import difflib
import fnmatch
import logging
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import optuna

from generalist_control.common.sections import SettingError, lookup, positive
from generalist_control.tracking import mlflow_utils

__all__ = [
    "CHANGES_ATTR",
    "FIXED_ATTR",
    "HeartbeatSettings",
    "PLAIN_NAME",
    "Param",
    "SearchSettings",
    "StudyConfigChangedError",
    "check_fixed_config",
    "config_diff",
    "fixed_config",
    "parse_space",
]

log = logging.getLogger(__name__)

#: A study name: also a folder name (no separator, no ``..``) and an MLflow filter value.
PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")

_SPEC_KEYS = {
    "categorical": {"type", "choices"},
    "int": {"type", "low", "high", "step", "log"},
    "float": {"type", "low", "high", "step", "log"},
}


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

    ``sampler`` and ``pruner`` are ``_target_`` mappings of Optuna classes (null: Optuna's
    default sampler, no pruning); ``params`` is the search space's tree (:func:`parse_space`).
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


@dataclass(frozen=True)
class Param:
    """One dimension of the search space: a dotted config key (also the Optuna name) and its law.

    ``type`` is ``categorical`` (``choices``), ``int`` or ``float`` (``low`` and ``high``
    included, an optional grid ``step``, ``log`` scale).
    """

    key: str
    type: str
    choices: tuple[Any, ...] | None = None
    low: float | None = None
    high: float | None = None
    step: float | None = None
    log: bool = False

    def suggest(self, trial: optuna.Trial) -> Any:
        """Draw this parameter's value for ``trial``."""
        if self.type == "categorical":
            return trial.suggest_categorical(self.key, list(self.choices or ()))
        low, high = float(self.low or 0), float(self.high or 0)  # set for int and float
        if self.type == "int":
            step = int(self.step) if self.step else 1
            return trial.suggest_int(self.key, int(low), int(high), step=step, log=self.log)
        return trial.suggest_float(self.key, low, high, step=self.step, log=self.log)


def parse_space(params: Mapping[str, Any], tree: Mapping[str, Any]) -> list[Param]:
    """Validate ``hparams_search.params`` against the config; return the search space.

    ``params`` is the config's tree down to the searched keys, each ending in a distribution
    (``{model: {hidden: {type: categorical, choices: [...]}}}``); each must name a value of
    ``tree``, the composed config.

    Raises
    ------
    KeyError
        A key that the config does not have (with the closest existing keys).
    ValueError
        An empty space, a key naming a config section, or a malformed distribution.
    """
    specs = _specs(params, "")
    if not specs:
        raise ValueError("hparams_search.params is empty: nothing to search")
    space = []
    for key, spec in specs.items():
        found, node = lookup(tree, key)
        if not found:
            leaves = list(mlflow_utils.flatten_params(tree, exclude=()))
            close = difflib.get_close_matches(key, leaves, n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise KeyError(f"unknown search-space key {key!r}: the config has no such key{hint}")
        if isinstance(node, Mapping):
            raise ValueError(f"search-space key {key!r} names a config section, not a value")
        space.append(_param(key, spec))
    return space


def _specs(node: Any, prefix: str) -> dict[str, Any]:
    """``{dotted key: distribution}`` from the nested ``params`` tree."""
    if node is None:
        return {}
    if not isinstance(node, Mapping):
        raise ValueError(
            f"hparams_search.params.{prefix} must be a distribution (a mapping with a "
            f"'type') or a mapping of them, not {node!r}"
        )
    if "type" in node:
        return {prefix: node}
    out: dict[str, Any] = {}
    for key, value in node.items():
        out.update(_specs(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def _param(key: str, spec: Mapping[str, Any]) -> Param:
    """The :class:`Param` of one distribution, checked."""
    where = f"hparams_search.params.{key}"
    kind = spec.get("type")
    if kind not in _SPEC_KEYS:
        raise ValueError(f"{where}.type must be one of {sorted(_SPEC_KEYS)}, not {kind!r}")
    extra = set(spec) - _SPEC_KEYS[kind]
    if extra:
        raise ValueError(f"{where}: unknown field(s) {sorted(extra)} for type {kind!r}")
    if kind == "categorical":
        choices = spec.get("choices")
        if not choices or isinstance(choices, str):
            raise ValueError(f"{where}.choices must be a non-empty list")
        return Param(key, kind, choices=tuple(choices))
    low, high = spec.get("low"), spec.get("high")
    if low is None or high is None or not low < high:
        raise ValueError(f"{where} needs low < high, got low={low!r}, high={high!r}")
    log_scale = bool(spec.get("log"))
    if log_scale and low <= 0:
        raise ValueError(f"{where}: a log-scale range needs low > 0, got {low!r}")
    return Param(key, kind, low=low, high=high, step=spec.get("step"), log=log_scale)


#: Study user attribute: ``{dotted key: value}`` of the fixed config.
FIXED_ATTR = "fixed_config"
#: Study user attribute: the accepted changes (``allow_config_change``), oldest first.
CHANGES_ATTR = "fixed_config_changes"
_ABSENT = "(absent or searched)"


class StudyConfigChangedError(ValueError):
    """A study is resumed under a fixed config other than the one it was created with."""


def fixed_config(
    tree: Mapping[str, Any], metric: str, searched: Iterable[str], identity: Sequence[str]
) -> dict[str, str]:
    """What shapes a trial apart from the searched keys, as ``{dotted key: text}``.

    ``tree`` is the trials' resolved config less ``hparams_search``, of which only the
    ``metric`` is kept; the ``searched`` keys and those matching an ``identity`` pattern
    (:mod:`fnmatch`, keys that name or place a run: ``logger.*``) are left out.
    """
    flat = mlflow_utils.flatten_params(tree, exclude=("hydra",))
    flat["hparams_search.metric"] = metric
    skip = set(searched)
    return {
        key: value
        for key, value in sorted(flat.items())
        if key not in skip and not any(fnmatch.fnmatchcase(key, p) for p in identity)
    }


def config_diff(old: Mapping[str, Any], new: Mapping[str, Any]) -> dict[str, tuple[str, str]]:
    """``{key: (old, new)}`` of the keys whose value differs (absent on one side counts).

    Examples
    --------
    >>> config_diff({"a": "1", "b": "2"}, {"a": "1", "b": "3", "c": "4"})
    {'b': ('2', '3'), 'c': ('(absent or searched)', '4')}
    """
    keys = sorted(set(old) | set(new))
    return {
        k: (str(old.get(k, _ABSENT)), str(new.get(k, _ABSENT)))
        for k in keys
        if old.get(k, _ABSENT) != new.get(k, _ABSENT)
    }


def check_fixed_config(
    study: optuna.Study, fixed: Mapping[str, str], allow_change: bool
) -> dict[str, tuple[str, str]]:
    """Record ``fixed`` on a new study; on a resumed one, compare it with the recorded one.

    With ``allow_change`` (``hparams_search.allow_config_change``) a change is warned of,
    appended to the user attribute ``fixed_config_changes`` and the new config recorded.
    Returns the differences accepted, ``{key: (old, new)}``.

    Raises
    ------
    StudyConfigChangedError
        The fixed config differs and ``allow_change`` is false; nothing was written.
    """
    old = study.user_attrs.get(FIXED_ATTR)
    n_trials = len(study.get_trials(deepcopy=False))
    if old is None:
        if n_trials:
            log.warning(
                "study %r has %d trials but no recorded fixed config (created before it was "
                "recorded); recording the current one",
                study.study_name,
                n_trials,
            )
        study.set_user_attr(FIXED_ATTR, dict(fixed))
        return {}
    diff = config_diff(old, fixed)
    if not diff:
        return {}
    lines = "\n".join(f"  {key}: {a} -> {b}" for key, (a, b) in diff.items())
    head = (
        f"study {study.study_name!r} ({n_trials} trials) was created with another fixed "
        f"config (what shapes a trial apart from the searched keys); its old and new trials "
        f"would not be comparable. Changed (old -> new):\n{lines}\n"
    )
    if not allow_change:
        raise StudyConfigChangedError(
            head + "Start a new study with hparams_search.study_name=<new name>, or continue "
            "this one anyway with hparams_search.allow_config_change=true."
        )
    log.warning("%sContinuing (hparams_search.allow_config_change=true).", head)
    change = {
        "at": mlflow_utils.now(),
        "n_trials_before": n_trials,
        "changed": {k: list(v) for k, v in diff.items()},
    }
    study.set_user_attr(CHANGES_ATTR, [*(study.user_attrs.get(CHANGES_ATTR) or []), change])
    study.set_user_attr(FIXED_ATTR, dict(fixed))
    return diff
