"""A plant given at run time (the model card route): a plant YAML anywhere, or a model dict.

Both are checked as a catalogue plant is; ``tag``, ``description`` and ``source`` may be left out.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from generalist_control.plants.config import plant_from_config
from generalist_control.plants.definition import Plant, PlantConfigError

__all__ = ["MODEL_KEYS", "plant_from_file", "plant_from_model"]

#: The keys of a model dict (``name`` optional).
MODEL_KEYS = ("A", "B", "C", "dt", "Q", "R")

#: What a plant given at run time need not say: it gets a row of its own; its tag is unused.
_DEFAULTS = {"tag": 0, "description": "a plant given at run time", "source": "given"}


def plant_from_model(model: Mapping[str, Any], name: str | None = None) -> Plant:
    """A :class:`Plant` from a model dict (keys :data:`MODEL_KEYS`, ``name`` optional).

    E.g. ``{"A": [[0, 1], [-2, -3]], "B": [[0], [1]], "C": [[1, 0]], "dt": 0.05,
    "Q": [1, 1, 10], "R": 1.0}``.

    Raises
    ------
    PlantConfigError
        A missing or unknown key, a matrix of the wrong shape, NaN or inf, weights that are
        not (semi)definite; the message names the key.
    """
    label = str(name or model.get("name") or "given")
    where = f"model dict '{label}'"
    missing = [k for k in MODEL_KEYS if k not in model]
    unknown = sorted(set(model) - {*MODEL_KEYS, "name"})
    if missing or unknown:
        raise PlantConfigError(
            f"{where}: needs the keys {list(MODEL_KEYS)} (and optionally 'name'); "
            + (f"missing {missing}" if missing else f"unknown {unknown}")
        )
    try:
        n = len(model["A"])
    except TypeError:
        raise PlantConfigError(
            f"{where}: field 'A' must be a square matrix (a list of rows)"
        ) from None
    cfg = {
        **_DEFAULTS,
        "dt": model["dt"],
        "states": [{"name": f"x{i + 1}", "unit": "-"} for i in range(n)],
        "input": {"name": "u", "unit": "-"},
        "output": {"name": "y", "unit": "-"},
        **{k: model[k] for k in ("A", "B", "C")},
        "lqi": {"Q": model["Q"], "R": model["R"]},
    }
    return plant_from_config(label, cfg)


def plant_from_file(path: str | Path) -> Plant:
    """A :class:`Plant` from a plant YAML file (its name: the file's stem).

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    PlantConfigError
        If the file is not a plant (not a mapping, a field missing or malformed).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no plant file at {path}")
    try:
        cfg = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise PlantConfigError(f"{path} is not YAML ({type(exc).__name__})") from None
    if not isinstance(cfg, dict) or not ({"A", "dynamics"} & set(cfg)):
        raise PlantConfigError(
            f"{path} is not a plant file: a plant YAML is a mapping with the model (A, B, C "
            "or dynamics), dt, states, input, output and lqi (conf/plants/README.md)"
        )
    return plant_from_config(path.stem, {**_DEFAULTS, **cfg})
