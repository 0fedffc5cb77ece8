"""Evaluation on unseen plant variants (``evaluation.variants``, ``experiment=variants``).

For each plant, ``count`` variants are drawn with the evaluation's own seed
(:func:`generalist_control.simulation.variants.sample_variants`); none may equal a training
variant: their factor vectors are compared with every variant the policy's data recorded in
its manifest (``paths.data_dir``), or, without such a manifest, with the draws of the data
config's seed stream, and the evaluation's seed must differ from the data's. On every
variant and scenario (``evaluation.variants.scenarios``, names of ``evaluation.scenarios``)
three controllers run in lockstep with the evaluation's simulator: ``GC`` (the policy, told
the nominal plant's tag), ``LQI`` (the variant's own LQI, the oracle) and ``LQI-nominal``
(the nominal plant's LQI gains on the variant, what a user has without redesign).

Outputs (``paths.reports_dir``): ``metrics.csv`` (system, variant, scenario, controller, run,
metric, value), ``summary.json`` (the issue's bars, each with its verdict;
:mod:`~generalist_control.evaluation.variant_summary`), ``variants.csv`` (each variant's
parameters and factors) and plots. With ``evaluation.variants.validation`` (on by default), a
held-out check: the same bar on a second draw of other variants (its own seed and count) on
the judged scenario, in ``summary.json``'s ``validation`` block and ``validation.csv``; the
top-level verdict stays the test draw's.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.common.atomic import (
    check_replaceable,
    publish_directory,
    staging_directory,
)
from generalist_control.common.configs import as_dict
from generalist_control.common.jsonsafe import strict
from generalist_control.data.demos import read_manifest
from generalist_control.data.variants import variants_config
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.runner import metric_rows
from generalist_control.evaluation.setpoint import setpoint_from_config, setpoint_summary
from generalist_control.evaluation.variant_summary import plot_variants, summarise_variants
from generalist_control.plants.plant import Plant
from generalist_control.plants.variants import DEFAULT_RANGE, variant_range
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.scenarios import perturbation, references
from generalist_control.simulation.simulate import (
    BatchController,
    PerPlantController,
    Run,
    simulate_many,
)
from generalist_control.simulation.variants import (
    Variant,
    VariantDraw,
    candidate_factors,
    sample_variants,
)

__all__ = [
    "CONTROLLERS",
    "OWNED",
    "check_disjoint",
    "check_variants_dir",
    "draw_eval_variants",
    "evaluate_variants",
    "run_variants",
]

CONTROLLERS = ("GC", "LQI", "LQI-nominal")
COLUMNS = ["system", "variant", "scenario", "controller", "run", "metric", "value"]

#: What a variants report folder holds: the only entries its evaluation may replace.
OWNED: dict[str, str | None] = {
    "metrics.csv": None,
    "summary.json": None,
    "validation.csv": None,
    "variants.csv": None,
    "setpoint.csv": None,
    "plots": "*.png",
}


def check_variants_dir(out_dir: str | Path) -> None:
    """Refuse (before any work) a ``paths.reports_dir`` that holds other files."""
    check_replaceable(out_dir, OWNED, "paths.reports_dir")


def draw_eval_variants(
    plants: Sequence[Plant],
    ecfg: Mapping[str, Any],
    steps: int,
    key: str = "evaluation.variants.range",
) -> dict[str, VariantDraw]:
    """``ecfg.count`` (at least 5) variants per plant from the evaluation's seed.

    ``ecfg.range`` must be a number in (0, 1) (an error names ``key``).
    """
    count = int(ecfg.get("count", 6))
    if count < 5:
        raise ValueError(f"evaluation.variants.count = {count}: the bar needs at least 5")
    rng = variant_range(ecfg.get("range"), key)
    seed, tries = int(ecfg["seed"]), int(ecfg.get("max_tries", 10))
    return {
        p.name: sample_variants(p, count, seed, rng, (1.0, -1.0), steps, tries) for p in plants
    }


def _training_factors(
    plants: Sequence[Plant], data: Mapping[str, Any], data_dir: Path
) -> tuple[str, dict[str, list[dict[str, float]]]]:
    """The training variants' factors, from the data's manifest or its config's seed stream."""
    manifest = data_dir / "manifest.json"
    if manifest.is_file():
        recorded = read_manifest(data_dir).get("variants")  # checked against its digest
        if recorded:
            return f"manifest {manifest}", {
                name: [v["factors"] for v in rec["kept"]] for name, rec in recorded.items()
            }
    vcfg = variants_config({**data, "variants": {**(data.get("variants") or {}), "enabled": 1}})
    assert vcfg is not None
    n = vcfg["count"] * vcfg["max_tries"]  # every candidate the data stage may have drawn
    out = {p.name: _candidates(p, [vcfg["seed"]], vcfg["range"], n) for p in plants}
    return f"seed stream data.variants.seed={vcfg['seed']}", out


def _candidates(
    plant: Plant, seeds: Sequence[int], default_range: float, n: int
) -> list[dict[str, float]]:
    """The first ``n`` candidates of each seed's stream (:func:`candidate_factors`)."""
    return [
        f for s in seeds for f in itertools.islice(candidate_factors(plant, s, default_range), n)
    ]


def _dagger_factors(
    plants: Sequence[Plant], data: Mapping[str, Any], dagger: Mapping[str, Any]
) -> tuple[range, dict[str, list[dict[str, float]]]]:
    """The seeds and candidate factors of DAgger's fresh variants (``variants.fresh``).

    Every candidate a round may have drawn (kept or refused), from its seed stream
    (:meth:`~generalist_control.training.sampler.RolloutSampler.round_plants`; range and
    tries the data's, as :func:`~generalist_control.training.setup.dagger_callback` sets
    them). ``dagger``: the ``dagger`` config section ({} when it is off).
    """
    spec = (dagger.get("sampler") or {}).get("variants") or {}
    fresh = int(spec.get("fresh", 0) or 0)
    if fresh < 1:
        return range(0), {}
    block = data.get("variants") or {}
    rng = float(block.get("range", DEFAULT_RANGE))
    tries = int(block.get("max_tries", 10))
    seed = int(spec.get("seed", 3001))
    seeds = range(seed, seed + int(dagger.get("rounds", 0)))
    return seeds, {p.name: _candidates(p, seeds, rng, fresh * tries) for p in plants}


def check_disjoint(
    draws: Mapping[str, VariantDraw],
    plants: Sequence[Plant],
    data: Mapping[str, Any],
    data_dir: Path,
    seed: int,
    dagger: Mapping[str, Any] | None = None,
    key: str = "evaluation.variants.seed",
) -> dict[str, Any]:
    """Refuse evaluation variants equal to a training variant; return what was checked.

    The training variants are the data's and, with ``dagger.sampler.variants.fresh``, every
    candidate DAgger's rounds may have drawn. ``key`` names the seed in the messages.

    Raises
    ------
    ValueError
        The evaluation's seed is the data's or one of DAgger's, or a drawn factor vector
        equals a training one.
    """
    if seed == int((data.get("variants") or {}).get("seed", -1)):
        raise ValueError(
            f"{key} = {seed} is data.variants.seed: choose another, so the evaluation's "
            "variants are not the training's"
        )
    seeds, fresh = _dagger_factors(plants, data, dagger or {})
    if seed in seeds:
        raise ValueError(
            f"{key} = {seed} is one of DAgger's fresh-variant seeds "
            f"({seeds.start}..{seeds.stop - 1}): choose another, or move "
            "dagger.sampler.variants.seed"
        )
    source, train = _training_factors(plants, data, data_dir)
    if fresh:
        source += f" and DAgger's fresh variants (seeds {seeds.start}..{seeds.stop - 1})"
        train = {n: train.get(n, []) + fresh.get(n, []) for n in {*train, *fresh}}
    gap = np.inf
    for name, draw in draws.items():
        for v in draw.kept:
            for f in train.get(name, []):
                d = max(abs(v.factors[k] - f.get(k, 1.0)) for k in v.factors)
                if d < 1e-9:
                    raise ValueError(
                        f"plant '{name}': evaluation variant {v.index} equals a training "
                        f"variant ({source}); change {key}"
                    )
                gap = min(gap, d)
    return {"checked_against": source, "min_factor_distance": float(gap)}


def _rows(
    v: Variant, scenario: str, ctrl: str, kind: str, tr: Any
) -> list[tuple[str, int, str, str, int, str, float]]:
    """The evaluation's long-form rows (:func:`metric_rows`) with the variant's index."""
    rows = metric_rows(v.plant.name, scenario, ctrl, kind, tr)
    return [(system, v.index, *rest) for system, *rest in rows]  # type: ignore[misc]


def _controller(
    name: str, runtime: PolicyRuntime, nominal: Mapping[str, Plant]
) -> BatchController:
    if name == "GC":
        return RuntimeAdapter(runtime)
    if name == "LQI":
        return PerPlantController(LQIController)  # each variant's own design
    return PerPlantController(lambda p: LQIController(p, design_lqi(nominal[p.name])))


def evaluate_variants(
    runtime: PolicyRuntime,
    draws: Mapping[str, VariantDraw],
    scenarios: Mapping[str, Mapping[str, Any]],
) -> pd.DataFrame:
    """Every controller on every variant and scenario; long-form metrics (:data:`COLUMNS`)."""
    variants = [v for d in draws.values() for v in d.kept]
    nominal = {name: d.nominal for name, d in draws.items()}
    rows: list[tuple] = []
    for name, spec in scenarios.items():
        chosen = [
            v
            for v in variants
            if spec.get("plants") in (None, []) or v.plant.name in spec["plants"]
        ]
        runs = [
            Run(v.plant, *references(name, spec, v.plant), perturbation(name, spec, v.plant))
            for v in chosen
        ]
        for ctrl in CONTROLLERS:
            results = simulate_many(runs, _controller(ctrl, runtime, nominal))
            for v, tr in zip(chosen, results, strict=True):
                rows += _rows(v, name, ctrl, spec["kind"], tr)
    return pd.DataFrame(rows, columns=COLUMNS)


def _variants_table(draws: Mapping[str, VariantDraw]) -> pd.DataFrame:
    rows = []
    for name, d in draws.items():
        for v in d.kept:
            rec = v.record()
            for key, value in rec["parameters"].items():  # type: ignore[attr-defined]
                factor = v.factors.get(key, 1.0)
                rows.append((name, v.index, key, value, factor))
    return pd.DataFrame(rows, columns=["system", "variant", "parameter", "value", "factor"])


def run_variants(
    cfg: Any,
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    record: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Draw, check, evaluate and write the variants report to ``paths.reports_dir``.

    ``record`` (which policy was evaluated, when and where:
    :mod:`~generalist_control.evaluation.provenance`) is added to ``summary.json``.
    """
    out_dir = Path(cfg.paths.reports_dir)
    check_variants_dir(out_dir)
    ecfg = as_dict(cfg.evaluation.variants)
    all_scen = as_dict(cfg.evaluation.scenarios)
    names = list(ecfg.get("scenarios") or ["step"])
    missing = [n for n in names if n not in all_scen]
    if missing:
        raise KeyError(
            f"evaluation.variants.scenarios names {missing}, not in evaluation.scenarios"
        )
    scen = {n: all_scen[n] for n in names}
    vcfg = _validation_config(ecfg)
    steps = int(round(float(scen[names[0]].get("duration", 15.0)) / plants[0].dt))
    training = (as_dict(cfg.data), as_dict(cfg.get("dagger") or {}), Path(cfg.paths.data_dir))
    draws, df, summary = _judge(runtime, plants, ecfg, scen, steps, training)
    summary["rejected"] = {n: d.rejected for n, d in draws.items() if d.rejected}
    val = None
    if vcfg is not None:  # the held-out check: the judged scenario on a second draw
        _, val, held = _judge(
            runtime, plants, vcfg, {names[0]: scen[names[0]]}, steps, training,
            "evaluation.variants.validation.seed",
        )  # fmt: skip
        summary["validation"] = {**held, "seed": int(vcfg["seed"]), "count": int(vcfg["count"])}
    setpoint = setpoint_from_config(as_dict(cfg.evaluation.get("setpoint") or {}), runtime, plants)
    if setpoint is not None:  # the nominal plants' set points
        summary["setpoint"] = setpoint_summary(setpoint)
    summary.update(record or {})
    with staging_directory(out_dir) as staging:
        df.to_csv(staging / "metrics.csv", index=False)
        if setpoint is not None:
            setpoint.to_csv(staging / "setpoint.csv", index=False)
        if val is not None:
            val.to_csv(staging / "validation.csv", index=False)
        _variants_table(draws).to_csv(staging / "variants.csv", index=False)
        (staging / "summary.json").write_text(json.dumps(strict(summary), indent=2) + "\n")
        if bool(cfg.evaluation.get("plots", True)):
            plot_variants(df, names[0], staging / "plots")
        publish_directory(staging, out_dir, OWNED, "paths.reports_dir")
    return summary


def _validation_config(ecfg: Mapping[str, Any]) -> dict[str, Any] | None:
    """The held-out draw's config (``evaluation.variants.validation`` over the test's).

    Raises
    ------
    ValueError
        Its seed is the test variants' seed.
    """
    if not ecfg.get("validation"):
        return None
    vcfg = {**ecfg, **as_dict(ecfg["validation"])}
    if int(vcfg["seed"]) == int(ecfg["seed"]):
        raise ValueError(
            f"evaluation.variants.validation.seed = {vcfg['seed']} is the test variants' seed: "
            "choose another, so the held-out check draws other variants"
        )
    return vcfg


def _judge(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    ecfg: Mapping[str, Any],
    scenarios: Mapping[str, Mapping[str, Any]],
    steps: int,
    training: tuple[Mapping[str, Any], Mapping[str, Any], Path],
    key: str = "evaluation.variants.seed",
) -> tuple[dict[str, VariantDraw], pd.DataFrame, dict[str, Any]]:
    """Draw ``ecfg``'s variants, check them against training, evaluate, summarise.

    ``training`` is the data config, the DAgger config and the data folder
    (:func:`check_disjoint`, whose messages name ``key``); the bars judge the first of
    ``scenarios``. Returns the draws, the long-form metrics and the summary (bars,
    verdicts, per plant, ``disjoint``).
    """
    data, dagger, data_dir = training
    draws = draw_eval_variants(plants, ecfg, steps, key.rsplit(".", 1)[0] + ".range")
    disjoint = check_disjoint(draws, plants, data, data_dir, int(ecfg["seed"]), dagger, key)
    df = evaluate_variants(runtime, draws, scenarios)
    summary = summarise_variants(df, next(iter(scenarios)), as_dict(ecfg.get("bar") or {}))
    summary["disjoint"] = disjoint
    return draws, df, summary
