"""The fixed part of a study's config: recorded when the study is created, checked on resume.

A study's score ranks trials only while everything but the searched keys stays the same (a
1-epoch study resumed with 60 epochs would rank unlike trials): another fixed config is refused.
"""

from __future__ import annotations

import fnmatch
import logging
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import optuna

from generalist_control.tracking import mlflow_utils

__all__ = [
    "CHANGES_ATTR",
    "FIXED_ATTR",
    "StudyConfigChangedError",
    "check_fixed_config",
    "config_diff",
    "fixed_config",
]

log = logging.getLogger(__name__)

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
