"""The config's types: the Hydra schema of the ``model`` group and strict value checks.

Hydra composes ``conf/`` untyped, so ``model.hidden=32.9`` would arrive as a float that a
bare ``int()`` truncates to 32 while MLflow logs 32.9. Two guards stop that, both before
anything is read, logged or trained:

* **At composition**, :class:`ModelSchema` types every key of the ``model`` group (an
  override that does not fit fails there, naming the key, the value and the type). This
  module stores it in Hydra's ConfigStore as ``gc_schema/model`` when it is imported (the
  entry points import it through :mod:`generalist_control.model.network`, and ``generate``
  directly), and every ``conf/model/*.yaml`` names it first in its defaults list as
  ``optional /gc_schema@_here_: model``. A composition that has not imported it (DVC's own
  Hydra, a bare ``compose`` in another program) still works, untyped.
* **At run time**, :func:`require_int`, :func:`require_switch` and :func:`require_fraction`,
  which :func:`~generalist_control.model.network.network_config` (``model.*``, ``experts``,
  ``data.history``, ``data.horizon``) and the training's data module (``loader.*``) apply
  to every value they receive, whatever composed the config. ``experts`` and ``loader``
  live in the primary config, whose defaults list names no schema: the run-time checks are
  theirs alone.

Integers are strict in both: a float is refused even when it is whole (``32.0``), and so is
a boolean (``true`` is not a size). The one difference: OmegaConf converts a quoted string
of digits (``model.hidden='32'``) to 32 at composition, while the run-time check, which
sees only what composition left, refuses any string.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

__all__ = [
    "SCHEMA_GROUP",
    "ModelSchema",
    "register_schemas",
    "require_fraction",
    "require_int",
    "require_switch",
]

#: The ConfigStore group of the schemas (``conf/model/*.yaml`` name ``/gc_schema: model``).
SCHEMA_GROUP = "gc_schema"


@dataclass
class ModelSchema:
    """Types of the ``model`` group's keys (values come from ``conf/model/*.yaml``).

    Every key is mandatory (``???``): a model config file sets them all, and the schema
    holds no second copy of their values. ``experts`` (M) is a top-level key and
    ``history``, ``horizon`` come from ``data``; see
    :data:`~generalist_control.model.network.MODEL_DEFAULTS` for their meaning.
    """

    hidden: int = MISSING
    heads: int = MISSING
    stride: int = MISSING
    n_tags: int = MISSING
    window_scale: bool = MISSING
    linear_head: bool = MISSING
    integral: bool = MISSING
    linear_samples: int = MISSING
    linear_init: str = MISSING
    linear_skip: bool = MISSING
    tag_free: bool = MISSING
    tag_dropout: float = MISSING
    history_context: bool = MISSING
    control_history: bool = MISSING
    skip_gain_scale: bool = MISSING
    identity_loss: float = MISSING
    infer_tag: bool = MISSING
    law_history: int = MISSING
    transition_identifier: bool = MISSING
    transition_models: bool = MISSING
    transition_input_gain: bool = MISSING
    transition_input_lag: bool = MISSING
    transition_input_offset: bool = MISSING
    identity_noise: float = MISSING
    identity_noise_clean_fit: bool = MISSING
    optimizer: dict[str, Any] = MISSING
    scheduler: dict[str, Any] | None = None


def register_schemas() -> None:
    """Store the schemas in Hydra's ConfigStore (idempotent; done on import)."""
    ConfigStore.instance().store(group=SCHEMA_GROUP, name="model", node=ModelSchema)


register_schemas()


def _kind(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})"


def require_int(key: str, value: Any, minimum: int = 1) -> int:
    """``value`` as an ``int`` if it is an integer ``>= minimum``; else a ``ValueError``.

    Python and NumPy integers pass; floats (even ``32.0``), booleans and strings do not.

    Examples
    --------
    >>> require_int("model.hidden", 32)
    32
    >>> require_int("model.hidden", 32.9)
    Traceback (most recent call last):
    ...
    ValueError: model.hidden must be an integer, got 32.9 (float)
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{key} must be an integer, got {_kind(value)}")
    if value < minimum:
        what = {0: "a non-negative integer", 1: "a positive integer"}.get(
            minimum, f"an integer >= {minimum}"
        )
        raise ValueError(f"{key} must be {what}, got {value}")
    return int(value)


def require_switch(key: str, value: Any) -> int:
    """``value`` as 0 or 1 if it is a boolean or the integer 0 or 1; else a ``ValueError``."""
    if isinstance(value, numbers.Integral) and value in (0, 1):
        return int(value)
    raise ValueError(f"{key} must be 0 or 1 (false/true), got {_kind(value)}")


def require_nonnegative(key: str, value: Any, what: str = "number") -> float:
    """``value`` as a ``float`` if it is a finite real number ``>= 0``; else a ``ValueError``.

    ``what`` names the quantity in the message (``"a finite fraction >= 0"``).

    Examples
    --------
    >>> require_nonnegative("dagger.noise", 0.05, "fraction")
    0.05
    >>> require_nonnegative("dagger.noise", -1, "fraction")
    Traceback (most recent call last):
    ...
    ValueError: dagger.noise must be a finite fraction >= 0, got -1 (int)
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{key} must be a finite {what} >= 0, got {_kind(value)}")
    number = float(value)
    if not (math.isfinite(number) and number >= 0.0):
        raise ValueError(f"{key} must be a finite {what} >= 0, got {_kind(value)}")
    return number


def require_fraction(key: str, value: Any) -> float:
    """``value`` as a ``float`` if it is a real number in ``[0, 1)``; else a ``ValueError``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{key} must be a number in [0, 1), got {_kind(value)}")
    fraction = float(value)
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"{key} must lie in [0, 1), got {value}")
    return fraction
