"""Sampling plant variants fit for LQI, with the reason for every one refused.

Kept: an equilibrium at ``x_op``, the nominal's class, a valid LQI design that does not
diverge on steps from rest.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from generalist_control.plants.definition import Plant, PlantConfigError, rhp_roots
from generalist_control.plants.variants import (
    VariantError,
    draw_factors,
    make_variant,
    nominal_parameters,
    parameter_ranges,
)
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.simulate import simulate

__all__ = [
    "Variant",
    "VariantDraw",
    "candidate_factors",
    "check_class",
    "check_variant",
    "sample_variants",
]


@dataclass(frozen=True)
class Variant:
    """A kept variant: its index (1, 2, ...; 0 is the nominal plant), plant and factors."""

    index: int
    plant: Plant
    factors: dict[str, float]

    def record(self) -> dict[str, object]:
        """Index, factors vs nominal, the parameter values (and u_op if nonlinear)."""
        out: dict[str, object] = {
            "index": self.index,
            "factors": self.factors,
            "parameters": nominal_parameters(self.plant),
        }
        if not self.plant.is_linear:
            out["u_op"] = self.plant.u_op
        return out


@dataclass(frozen=True)
class VariantDraw:
    """One plant's kept variants and every rejected candidate with its reason."""

    nominal: Plant
    kept: list[Variant]
    rejected: list[dict[str, object]] = field(default_factory=list)

    def record(self) -> dict[str, object]:
        """The manifest's entry for the plant."""
        return {
            "nominal": nominal_parameters(self.nominal),
            "kept": [v.record() for v in self.kept],
            "rejected": self.rejected,
        }


def check_class(variant: Plant, nominal: Plant) -> None:
    """Refuse (:class:`VariantError`) a variant with other RHP pole or zero counts than nominal."""
    # integrators come out within ~1e-8 of 0
    roots = [rhp_roots(p.A, p.B, p.C, 1e-6) for p in (variant, nominal)]
    for kind, got, want in zip(("poles", "zeros"), *roots, strict=True):
        if len(got) != len(want):
            where = f"rightmost at {max(got.real):+.4g}" if len(got) else "none"
            raise VariantError(
                f"it changes the plant's class: {len(got)} open-loop {kind} in the right "
                f"half-plane ({where}) against the nominal plant's {len(want)}"
            )


def check_variant(
    variant: Plant, amplitudes: Sequence[float], steps: int, nominal: Plant | None = None
) -> None:
    """Refuse (:class:`VariantError`) a variant unfit for LQI; ``nominal`` None: no class check."""
    if nominal is not None:
        check_class(variant, nominal)
    try:
        gains = design_lqi(variant)
    except PlantConfigError as exc:
        raise VariantError(f"LQI design refused it: {exc}") from exc
    amps = np.asarray(amplitudes, dtype=float) * variant.amplitude_scale
    if amps.size:
        tr = simulate(variant, LQIController(variant, gains), np.repeat(amps[:, None], steps, 1))
        if tr.diverged.any():
            bad = amps[tr.diverged].tolist()
            raise VariantError(f"its LQI loop diverges on steps of {bad} from rest")


def candidate_factors(plant: Plant, seed: int, default_range: float) -> Iterator[dict[str, float]]:
    """The endless, seeded stream of factor draws :func:`sample_variants` takes candidates from."""
    ranges = parameter_ranges(plant, default_range)
    rng = np.random.default_rng([int(seed), plant.tag])
    while True:
        yield draw_factors(ranges, rng)


def sample_variants(
    plant: Plant,
    count: int,
    seed: int,
    default_range: float,
    amplitudes: Sequence[float] = (1.0,),
    steps: int = 200,
    max_tries: int = 10,
) -> VariantDraw:
    """``count`` variants of ``plant`` fit for LQI, drawn from ``seed`` (and the plant's tag).

    ``default_range`` is the range of parameters the plant file does not set; each
    candidate's LQI must not diverge on steps of ``amplitudes`` over ``steps`` samples.

    Raises
    ------
    VariantError
        If fewer than ``count`` fit within ``max_tries * count`` draws, with the reasons.
    """
    ranges = parameter_ranges(plant, default_range)
    if not ranges:
        raise VariantError(
            f"plant '{plant.name}' has no perturbable parameter (all fixed by its ranges); "
            "give it a 'variants.range' > 0 in conf/plants/" + plant.name + ".yaml"
        )
    stream = candidate_factors(plant, seed, default_range)
    kept: list[Variant] = []
    rejected: list[dict[str, object]] = []
    for _ in range(max(1, int(max_tries)) * count):
        if len(kept) == count:
            break
        factors = next(stream)
        try:
            candidate = make_variant(plant, factors)
            check_variant(candidate, amplitudes, steps, plant)
        except VariantError as exc:
            rejected.append({"factors": factors, "reason": str(exc)})
            continue
        kept.append(Variant(len(kept) + 1, candidate, factors))
    if len(kept) < count:
        reasons = sorted({str(r["reason"]) for r in rejected})
        raise VariantError(
            f"plant '{plant.name}': only {len(kept)} of {count} variants are fit for LQI after "
            f"{len(kept) + len(rejected)} draws; reasons: {'; '.join(reasons[:3])}. Narrow its "
            f"range ('variants' in conf/plants/{plant.name}.yaml) or ask for fewer"
        )
    return VariantDraw(plant, kept, rejected)
