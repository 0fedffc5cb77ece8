"""Plant families: SISO linear plants drawn from a seeded distribution over plant classes.

A drawn transfer function is realised in drawn state coordinates (:data:`FORMS`) and units.
Candidate ``i`` of seed ``s`` depends on ``(s, i)`` alone; which are kept is decided in
:mod:`generalist_control.simulation.family_draw`. Design: ``docs/notes/plant-families.md``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from generalist_control.plants.definition import MAX_ORDER, Plant, Signal
from generalist_control.plants.lqi_weights import (
    BrysonRule,
    NoBandwidthError,
    Weights,
    bounds,
    log_uniform,
)

__all__ = [
    "CLASSES",
    "FORMS",
    "Candidate",
    "LinearFamily",
    "PlantFamily",
    "TransferModel",
    "plant_from_record",
    "realise",
]

#: The classes a family draws, each a feature of the transfer function.
CLASSES = (
    "well_damped",  # stable real poles and complex pairs with damping >= damping[0]
    "lightly_damped",  # a complex pair with damping in light_damping
    "integrating",  # one or two poles at s = 0
    "unstable",  # a real pole in the right half-plane
    "nonminimum_phase",  # a real zero in the right half-plane
    "slow_zero",  # a real left-half-plane zero slower than slow_zero[1] rad/s
)
#: Orders each class needs at least (a zero needs a pole more: plants are strictly proper).
MIN_ORDER = {"lightly_damped": 2, "nonminimum_phase": 2, "slow_zero": 2}
Range = tuple[float, float]


#: A chain of first/second-order stages of DC gain 1, the companion form, the chain rotated.
FORMS = ("cascade", "companion", "rotated")


@dataclass(frozen=True)
class TransferModel:
    """``gain`` (``s^m G(s)`` at 0), poles (a complex pair once), real zeros, classes."""

    gain: float
    poles: tuple[complex, ...]
    zeros: tuple[float, ...]
    classes: tuple[str, ...]

    @property
    def order(self) -> int:
        """Number of states: a complex pair counts twice."""
        return _size(self.poles)

    def record(self) -> dict[str, Any]:
        """JSON-ready: gain, poles as ``[re, im]``, zeros, classes."""
        return {
            "gain": self.gain,
            "poles": [[p.real, p.imag] for p in self.poles],
            "zeros": list(self.zeros),
            "classes": list(self.classes),
        }


def _sections(model: TransferModel, rng: np.random.Generator) -> list[tuple[np.ndarray, ...]]:
    """The chain's stages, input first: ``(num, den)`` each of DC gain 1 (or 1/s)."""
    dens = []
    for p in model.poles:
        if p.imag > 0:
            w2 = abs(p) ** 2
            dens.append((np.array([w2]), np.array([1.0, -2 * p.real, w2])))
        else:
            dens.append((np.array([1.0 if p == 0 else -p.real]), np.array([1.0, -p.real])))
    order = rng.permutation(len(dens))
    stages = [list(dens[i]) for i in order]
    for z in model.zeros:  # into the first stage with room; the last stays strictly proper
        for k, (num, den) in enumerate(stages):
            room = len(den) - len(num) - (1 if k == len(stages) - 1 else 0)
            if room > 0:
                stages[k][0] = np.polymul(num, [-1.0 / z, 1.0])
                break
    stages[0][0] = stages[0][0] * model.gain
    return [(num, den) for num, den in stages]


def _stage(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, ...]:
    """Controllable canonical form ``(A, B, C, D)`` of ``num/den`` (monic ``den``)."""
    k = len(den) - 1
    b = np.zeros(k + 1)
    b[k + 1 - len(num) :] = num
    a, b = den[::-1][:k], b[::-1]  # ascending powers
    A = np.zeros((k, k))
    A[:-1, 1:] = np.eye(k - 1)
    A[-1] = -a
    B = np.zeros((k, 1))
    B[-1, 0] = 1.0
    C = (b[:k] - b[k] * a)[None, :]
    return A, B, C, np.array([[b[k]]])


def realise(
    model: TransferModel, form: str, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A, B, C)`` of ``model`` in :data:`FORMS` ``form`` (``rng`` orders the stages)."""
    stages = _sections(model, rng)
    if form == "companion":
        num, den = np.array([1.0]), np.array([1.0])
        for n_, d_ in stages:
            num, den = np.polymul(num, n_), np.polymul(den, d_)
        A, B, C, _ = _stage(num, den)
        return A, B, C
    A, B, C, D = _stage(*stages[0])
    for num, den in stages[1:]:  # in series: the next stage is driven by this one's output
        A2, B2, C2, D2 = _stage(num, den)
        A = np.block([[A, np.zeros((A.shape[0], A2.shape[0]))], [B2 @ C, A2]])
        B, C, D = np.vstack([B, B2 @ D]), np.hstack([D2 @ C, C2]), D2 @ D
    if form == "rotated":
        T, r = np.linalg.qr(rng.standard_normal((A.shape[0], A.shape[0])))
        T = T * np.sign(np.diag(r))
        A, B, C = T @ A @ T.T, T @ B, C @ T.T
    return A, B, C


def scaled(
    A: np.ndarray,
    B: np.ndarray,
    C: np.ndarray,
    w: float,
    units: tuple[float, float],
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """States in drawn units: at ``w`` rad/s state ``i`` moves ``10^U`` times the output."""
    n = A.shape[0]
    x = np.linalg.solve(1j * w * np.eye(n) - A, B)[:, 0]
    y = complex((C @ x)[0])
    rel = np.abs(x / y)
    lo, hi = math.log(units[0]), math.log(units[1])
    scale = np.exp(rng.uniform(lo, hi, size=n)) / np.maximum(rel, 1e-300)
    return scale[:, None] * A / scale[None, :], scale[:, None] * B, C / scale[None, :]


@dataclass(frozen=True)
class Candidate:
    """Candidate ``index`` of a family: its model, realisation, weights and plant."""

    index: int
    model: TransferModel
    form: str
    weights: Weights | None  # None when the rule refused it (``reason``)
    plant: Plant | None
    reason: str | None = None

    def record(self, matrices: bool = True) -> dict[str, Any]:
        """JSON-ready parameters; with ``matrices``, the plant's ``A``, ``B``, ``C``."""
        out: dict[str, Any] = {"index": self.index, **self.model.record(), "form": self.form}
        if self.weights is not None:
            out.update(self.weights.record())
        if self.plant is not None and matrices:
            p = self.plant
            out.update(name=p.name, A=p.A.tolist(), B=p.B.tolist(), C=p.C.tolist())
        return out


class PlantFamily(Protocol):
    """What a family generator offers (:class:`LinearFamily`; a MIMO one later)."""

    @property
    def name(self) -> str:
        """The family's name (the plants' names start with it)."""

    @property
    def seed(self) -> int:
        """The seed of every candidate."""

    @property
    def dt(self) -> float:
        """The plants' sample time."""

    def candidate(self, index: int) -> Candidate:
        """Candidate ``index`` of the family's seed: a function of ``(seed, index)`` alone."""


def _weights(name: str, value: Mapping[Any, Any], known: Sequence[str]) -> dict[str, float]:
    out = {str(k): float(v) for k, v in dict(value).items()}
    unknown = sorted(set(out) - set(known))
    if unknown or not out or any(not (v >= 0 and math.isfinite(v)) for v in out.values()):
        raise ValueError(
            f"families.generator.{name} must map some of {list(known)} to weights >= 0, got "
            f"{value!r}" + (f" (unknown: {unknown})" if unknown else "")
        )
    if sum(out.values()) <= 0:
        raise ValueError(f"families.generator.{name}: the weights sum to 0")
    return out


@dataclass(frozen=True)
class LinearFamily:
    """SISO linear plants of order 1 to 4 across :data:`CLASSES`.

    Every field comes from config; ``conf/families/default.yaml`` says what each one means.
    """

    name: str
    seed: int
    dt: float
    inputs: int
    outputs: int
    orders: Mapping[int, float]
    classes: Mapping[str, float]
    extra_class: float
    forms: Mapping[str, float]
    time_constant: Range
    frequency: Range
    damping: Range
    light_damping: Range
    complex_share: float
    double_integrator: float
    unstable_pole: Range
    rhp_zero: Range
    slow_zero: Range
    lhp_zero: Range
    lhp_zero_share: float
    gain: Range
    state_scale: Range
    weights: BrysonRule = field(repr=False)

    def __post_init__(self) -> None:
        if (self.inputs, self.outputs) != (1, 1):
            raise ValueError(
                f"families.generator: inputs={self.inputs}, outputs={self.outputs}: MIMO "
                "families are not supported yet (the LQI expert, the data and the policy are "
                "SISO); set inputs: 1 and outputs: 1"
            )
        if not (isinstance(self.seed, int) and self.seed >= 0) or not self.dt > 0:
            raise ValueError("families.generator: seed must be an integer >= 0 and dt > 0")
        orders = {int(k): v for k, v in _weights("orders", self.orders, "1234").items()}
        if not set(orders) <= set(range(1, MAX_ORDER + 1)):
            raise ValueError(f"families.generator.orders: orders 1..{MAX_ORDER}, got {orders}")
        object.__setattr__(self, "orders", orders)
        for key, known in (("classes", CLASSES), ("forms", FORMS)):
            object.__setattr__(self, key, _weights(key, getattr(self, key), known))
        for key in ("extra_class", "complex_share", "double_integrator", "lhp_zero_share"):
            if not 0.0 <= float(getattr(self, key)) <= 1.0:
                raise ValueError(f"families.generator.{key} must lie in [0, 1]")
        for key in ("time_constant", "frequency", "unstable_pole", "rhp_zero", "slow_zero",
                    "lhp_zero", "gain", "state_scale", "damping", "light_damping"):  # fmt: skip
            object.__setattr__(self, key, bounds(key, getattr(self, key)))

    def candidate(self, index: int) -> Candidate:
        """Candidate ``index``: drawn from ``numpy.random.default_rng([seed, index])``."""
        rng = np.random.default_rng([self.seed, int(index)])
        model = self._model(rng)
        form = _pick(rng, self.forms)
        A, B, C = realise(model, form, rng)
        try:
            weights = self.weights.draw(A, B, C, rng)  # coordinate-free: any realisation
        except NoBandwidthError as exc:
            return Candidate(index, model, form, None, None, str(exc))
        A, B, C = scaled(A, B, C, weights.bandwidth, self.state_scale, rng)
        mats = (A, B, C, *weights.matrices(B, C))
        plant = _drawn_plant(self.name, self.seed, index, -1, model.classes, form, self.dt, *mats)
        return Candidate(index, model, form, weights, plant)

    def _model(self, rng: np.random.Generator) -> TransferModel:
        """Classes, then an order they fit in, then poles, zeros and gain."""
        classes = [_pick(rng, self.classes)]
        fits = {k: v for k, v in self.orders.items() if k >= MIN_ORDER.get(classes[0], 1)}
        if not fits:
            raise ValueError(f"families.generator.orders: none fits class '{classes[0]}'")
        n = int(_pick(rng, fits))
        others = {k: v for k, v in self.classes.items() if k not in (classes[0], "well_damped")}
        if rng.uniform() < self.extra_class and classes[0] != "well_damped" and others:
            extra = _pick(rng, others)
            if _fits(n, [*classes, extra]):
                classes.append(extra)
        poles, zeros = self._features(classes, n, rng)
        while _size(poles) < n:  # the rest: well damped
            if n - _size(poles) >= 2 and rng.uniform() < self.complex_share:
                poles.append(_pair(log_uniform(rng, self.frequency), rng, self.damping))
            else:
                poles.append(complex(-1.0 / log_uniform(rng, self.time_constant)))
        if len(zeros) < n - 1 and rng.uniform() < self.lhp_zero_share:
            zeros.append(-log_uniform(rng, self.lhp_zero))
        gain = log_uniform(rng, self.gain) * (1.0 if rng.uniform() < 0.5 else -1.0)
        named = tuple(c for c in CLASSES if c in classes)  # in the order of CLASSES
        return TransferModel(gain, tuple(poles), tuple(zeros), named)

    def _features(
        self, classes: list[str], n: int, rng: np.random.Generator
    ) -> tuple[list[complex], list[float]]:
        poles: list[complex] = []
        zeros: list[float] = []
        for c in sorted(classes, key=lambda c: c == "integrating"):  # its second pole: if room
            if c == "lightly_damped":
                poles.append(_pair(log_uniform(rng, self.frequency), rng, self.light_damping))
            elif c == "integrating":
                two = n - _size(poles) >= 2 and rng.uniform() < self.double_integrator
                poles += [0j, 0j] if two else [0j]
            elif c == "unstable":
                poles.append(complex(log_uniform(rng, self.unstable_pole)))
            elif c == "nonminimum_phase":
                zeros.append(log_uniform(rng, self.rhp_zero))
            elif c == "slow_zero":
                zeros.append(-log_uniform(rng, self.slow_zero))
        return poles, zeros


def _drawn_plant(
    family: str, seed: int, index: int, tag: int, classes: Sequence[str], form: str, dt: float,
    *mats: np.ndarray,
) -> Plant:  # fmt: skip
    A, B, C, Q, R = mats
    n = A.shape[0]
    return Plant(
        name=f"{family}_s{seed}_{index:05d}",
        tag=tag,
        description=f"drawn: order {n}, {' + '.join(classes)}, {form} form",
        source=f"plant family '{family}', seed {seed}, candidate {index}",
        states=tuple(Signal(f"x{i + 1}", "-") for i in range(n)),
        input_signal=Signal("u", "-"),
        output_signal=Signal("y", "-"),
        dt=dt, A=A, B=B, C=C, Q=Q, R=R, x_op=np.zeros(n),
    )  # fmt: skip


def plant_from_record(family: Mapping[str, Any], name: str, dt: float) -> Plant:
    """Plant ``name`` rebuilt, bit for bit, from a data manifest's ``plant_family`` block."""
    r = family["plants"][name]
    A, B, C = (np.array(r[k], dtype=float) for k in ("A", "B", "C"))
    weights = Weights(r["bandwidth"], r["integral_ratio"], r["q_y"], r["q_z"])
    mats = (A, B, C, *weights.matrices(B, C))
    return _drawn_plant(
        family["name"], family["seed"], r["index"], r["tag"], r["classes"], r["form"], dt, *mats
    )


def _size(poles: Sequence[complex]) -> int:
    return sum(2 if p.imag > 0 else 1 for p in poles)


def _fits(n: int, classes: Sequence[str]) -> bool:
    """Whether ``classes`` fit in order ``n``: poles they take, and a pole per zero."""
    poles = sum({"lightly_damped": 2, "integrating": 1, "unstable": 1}.get(c, 0) for c in classes)
    zeros = sum(c in ("nonminimum_phase", "slow_zero") for c in classes)
    return poles <= n and zeros <= n - 1 and n >= max(MIN_ORDER.get(c, 1) for c in classes)


def _pick(rng: np.random.Generator, weights: Mapping[Any, float]) -> Any:
    """A key of ``weights`` with probability proportional to its weight (one uniform draw)."""
    keys, total = list(weights), sum(weights.values())
    u, acc = rng.uniform() * total, 0.0
    for k in keys:
        acc += weights[k]
        if u < acc:
            return k
    return keys[-1]


def _pair(wn: float, rng: np.random.Generator, damping: Range) -> complex:
    zeta = float(rng.uniform(*damping))
    return complex(-zeta * wn, wn * math.sqrt(max(1.0 - zeta**2, 0.0)))
