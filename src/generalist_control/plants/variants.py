"""Plant variants: each perturbable parameter scaled by a factor uniform in ``[1 - r, 1 + r]``.

Perturbable: a nonlinear plant's ``dynamics.params``; a linear plant's non-zero ``A``, ``B``
entries but off-diagonal 1s. A plant file's ``variants`` block changes this
(``conf/plants/README.md``); rules and reasons: docs/notes/plant-variants.md.
"""

from __future__ import annotations

import dataclasses
import numbers
import weakref
from collections.abc import Mapping
from typing import Any

import numpy as np

from generalist_control.plants.definition import Plant, PlantConfigError, linearise

__all__ = [
    "DEFAULT_RANGE",
    "VariantError",
    "VariantSpec",
    "draw_factors",
    "make_variant",
    "nominal_parameters",
    "parameter_ranges",
    "register_spec",
    "variant_range",
]

#: Relative half-width of a parameter's range when neither the plant nor the config says.
DEFAULT_RANGE = 0.25


def variant_range(value: Any, key: str, zero: bool = False, default: bool = True) -> float:
    """The config's ``key`` as a variant range: a number in (0, 1); None: :data:`DEFAULT_RANGE`.

    With ``zero``, 0 is allowed too (it fixes a parameter); without ``default``, None is refused.

    Raises
    ------
    ValueError
        If it is not a number in (0, 1), naming ``key``.
    """
    if value is None and default:
        return DEFAULT_RANGE
    number = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if not number or not (0.0 <= float(value) < 1.0) or (float(value) == 0.0 and not zero):
        raise ValueError(
            f"{key} = {value!r} must be a number in {'[' if zero else '('}0, 1): the relative "
            f"half-width of the parameters' range, e.g. {DEFAULT_RANGE} for "
            f"+-{100 * DEFAULT_RANGE:g} %"
        )
    return float(value)


class VariantError(ValueError):
    """A variant is unfit (no equilibrium, unfit for LQI, ...); the message is the reason."""


@dataclasses.dataclass(frozen=True)
class VariantSpec:
    """A plant file's ``variants`` block (``range`` None: the config's)."""

    range: float | None = None
    ranges: Mapping[str, float] = dataclasses.field(default_factory=dict)
    include: frozenset[str] = frozenset()


_SPECS: weakref.WeakKeyDictionary[Plant, VariantSpec] = weakref.WeakKeyDictionary()


def _check_range(value: Any, field: str, name: str) -> float:
    """A plant file's range (0 allowed), refused as a :class:`PlantConfigError`."""
    try:
        return variant_range(value, f"plant '{name}': field '{field}'", zero=True, default=False)
    except ValueError as e:
        raise PlantConfigError(str(e)) from None


def register_spec(plant: Plant, block: Mapping[str, Any] | None) -> VariantSpec:
    """Validate a plant file's ``variants`` block and attach it to ``plant``.

    Raises
    ------
    PlantConfigError
        Unknown keys, a range outside [0, 1), or a name in ``ranges`` that is not one of
        the plant's non-zero parameters.
    """
    block = dict(block or {})
    unknown = sorted(set(block) - {"range", "ranges", "include"})
    if unknown:
        raise PlantConfigError(
            f"plant '{plant.name}': field 'variants' has unknown keys {unknown}; "
            "allowed: 'range', 'ranges', 'include'"
        )
    rng = block.get("range")
    default = None if rng is None else _check_range(rng, "variants.range", plant.name)
    known = nominal_parameters(plant)
    given = dict(block.get("ranges") or {})
    include = [str(k) for k in block.get("include") or []]
    for key in [*given, *include]:
        if key not in known:
            raise PlantConfigError(
                f"plant '{plant.name}': field 'variants' names '{key}', which is not one of "
                f"its non-zero parameters: {', '.join(known)}"
            )
    ranges = {
        str(k): _check_range(v, f"variants.ranges.{k}", plant.name) for k, v in given.items()
    }
    spec = VariantSpec(default, ranges, frozenset(include))
    _SPECS[plant] = spec
    return spec


def _entry_names(plant: Plant) -> dict[str, tuple[str, int, int]]:
    """The non-zero ``A``, ``B`` entries by name: ``A[i,j]``, ``B[i]``."""
    out = {}
    for i, j in zip(*np.nonzero(plant.A), strict=True):
        out[f"A[{i},{j}]"] = ("A", int(i), int(j))
    for i in np.flatnonzero(plant.B[:, 0]):
        out[f"B[{i}]"] = ("B", int(i), 0)
    return out


def nominal_parameters(plant: Plant) -> dict[str, float]:
    """Every parameter a variant may scale, by name: ``params`` or the non-zero A, B entries."""
    if not plant.is_linear:
        return {k: float(v) for k, v in plant.params.items()}
    return {k: float(getattr(plant, m)[i, j]) for k, (m, i, j) in _entry_names(plant).items()}


def parameter_ranges(plant: Plant, default: float = DEFAULT_RANGE) -> dict[str, float]:
    """The relative range of every perturbable parameter (range > 0), by name, sorted.

    The plant file's ``variants`` block overrides ``default`` (module docstring).
    """
    spec = _SPECS.get(plant, VariantSpec())
    base = default if spec.range is None else spec.range
    entries = _entry_names(plant) if plant.is_linear else {}
    out = {}
    for key, value in nominal_parameters(plant).items():
        m, i, j = entries.get(key, ("", 0, 0))
        fixed = m == "A" and value == 1.0 and i != j and key not in spec.include
        r = spec.ranges.get(key, 0.0 if fixed else base)
        if r > 0:
            out[key] = r
    return dict(sorted(out.items()))


def draw_factors(ranges: Mapping[str, float], rng: np.random.Generator) -> dict[str, float]:
    """One factor per parameter, uniform in ``[1 - r, 1 + r]``, drawn in sorted name order."""
    names = sorted(ranges)
    r = np.array([ranges[k] for k in names])
    u = rng.uniform(-1.0, 1.0, size=len(names))
    return {k: float(v) for k, v in zip(names, 1.0 + r * u, strict=True)}


def _solve_u_op(plant: Plant, params: Mapping[str, float]) -> float:
    """The input that best holds ``x_op`` (Gauss-Newton on ``|f(x_op, u)|``)."""
    assert plant.f is not None and plant.x_op is not None
    x = plant.x_op[None, :]
    u = float(plant.u_op)
    for _ in range(20):
        eps = 1e-6 * max(1.0, abs(u))
        f0 = plant.f(x, np.array([u]), **params)[0]
        b = (plant.f(x, np.array([u + eps]), **params)[0] - f0) / eps
        if not np.any(b):
            break
        du = -float(b @ f0) / float(b @ b)
        u += du
        if abs(du) <= 1e-14 * max(1.0, abs(u)):
            break
    return u


def _nonlinear_variant(plant: Plant, params: dict[str, float]) -> Plant:
    """The plant with ``params``, ``u_op`` re-solved to hold the nominal ``x_op``."""
    assert plant.f is not None and plant.x_op is not None
    u_op = _solve_u_op(plant, params)
    f0 = plant.f(plant.x_op[None, :], np.array([u_op]), **params)[0]
    A, B, C_lin = linearise(plant.f, plant.h, plant.x_op, u_op, params)
    scale = np.abs(A) @ np.abs(plant.x_op) + np.abs(B[:, 0]) * abs(u_op)
    if not np.all(np.isfinite(f0)) or np.any(np.abs(f0) > 1e-6 * scale + 1e-12):
        raise VariantError(
            f"no equilibrium at the nominal x_op = {plant.x_op.tolist()} for any input "
            f"(best u_op = {u_op:.6g} leaves f = {np.array2string(f0, precision=3)})"
        )
    C = C_lin if C_lin is not None else plant.C
    y_op = float(plant.h(plant.x_op[None, :], **params)[0]) if plant.h else plant.y_op
    return dataclasses.replace(plant, A=A, B=B, C=C, params=params, u_op=u_op, y_op=y_op)


def make_variant(plant: Plant, factors: Mapping[str, float]) -> Plant:
    """``plant`` with each named parameter multiplied by its factor (same name and tag).

    Raises
    ------
    KeyError
        A factor for a parameter the plant does not have.
    VariantError
        A nonlinear variant with no equilibrium at the nominal ``x_op``.
    """
    nominal = nominal_parameters(plant)
    unknown = sorted(set(factors) - set(nominal))
    if unknown:
        raise KeyError(f"plant '{plant.name}' has no parameters {unknown}")
    if not plant.is_linear:
        params = {k: v * float(factors.get(k, 1.0)) for k, v in nominal.items()}
        return _nonlinear_variant(plant, params)
    A, B = plant.A.copy(), plant.B.copy()
    for key, (m, i, j) in _entry_names(plant).items():
        target = A if m == "A" else B
        target[i, j] *= float(factors.get(key, 1.0))
    return dataclasses.replace(plant, A=A, B=B)
