"""The Optuna search space, read from ``hparams_search.params`` and checked against the config."""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import optuna

from generalist_control.tracking import mlflow_utils

__all__ = ["Param", "parse_space"]

_SPEC_KEYS = {
    "categorical": {"type", "choices"},
    "int": {"type", "low", "high", "step", "log"},
    "float": {"type", "low", "high", "step", "log"},
}


@dataclass(frozen=True)
class Param:
    """One dimension of the search space: a config key and its distribution.

    Parameters
    ----------
    key : str
        Dotted config key, e.g. ``model.hidden`` (also the Optuna parameter name).
    type : {"categorical", "int", "float"}
        The distribution.
    choices : tuple, optional
        Values of a categorical parameter.
    low, high : float, optional
        Bounds of an int or float parameter (both included).
    step : float, optional
        Grid step of an int or float parameter.
    log : bool
        Sample on a log scale (int and float).
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

    Parameters
    ----------
    params : mapping
        The config's tree down to the searched keys, each ending in a distribution (a
        mapping with a ``type``): ``{model: {hidden: {type: categorical, choices: [...]}}}``
        searches ``model.hidden``.
    tree : mapping
        The composed config the trials modify, as plain containers: every key must name a
        value in it.

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
        node: Any = tree
        for part in key.split("."):
            node = node.get(part, KeyError) if isinstance(node, Mapping) else KeyError
        if node is KeyError:
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


def _param(key: str, spec: Any) -> Param:
    where = f"hparams_search.params.{key}"
    if not isinstance(spec, Mapping):
        raise ValueError(f"{where} must be a mapping with a 'type', not {spec!r}")
    spec = dict(spec)
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
