"""Evaluation on unseen plant variants (``evaluation.variants``, ``experiment=variants``).

GC (told the nominal plant's tag), each variant's own LQI and the nominal LQI run on
variants none of which the training saw; docs/evaluation.md lists the outputs.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.common.jsonsafe import write_json
from generalist_control.data.demos import read_manifest
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.eval_config import EvaluationSettings, VariantEvalSettings
from generalist_control.evaluation.eval_run import EvalRun
from generalist_control.evaluation.runner import metric_rows, run_suite
from generalist_control.evaluation.setpoint import setpoint_summary
from generalist_control.evaluation.variant_summary import plot_variants, summarise_variants
from generalist_control.evaluation.writer import Record, check_reports_dir, publish_snapshot
from generalist_control.plants.definition import Plant
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.scenarios import perturbation, references, runs_on
from generalist_control.simulation.simulate import (
    BatchController,
    PerPlantController,
    Run,
    simulate_many,
)
from generalist_control.simulation.variant_sampling import (
    Variant,
    VariantDraw,
    candidate_factors,
    sample_variants,
)

__all__ = [
    "CONTROLLERS",
    "OWNED",
    "TrainingDraws",
    "check_disjoint",
    "evaluate_variants",
    "run_variants",
]

CONTROLLERS = ("GC", "LQI", "LQI-nominal")
COLUMNS = ["system", "variant", "scenario", "controller", "run", "metric", "value"]

#: What a variants report folder holds: the only entries its evaluation may replace.
OWNED: dict[str, str | None] = {
    "metrics.csv": None,
    "summary.json": None,
    "provenance.json": None,
    "validation.csv": None,
    "variants.csv": None,
    "setpoint.csv": None,
    "plots": "*.png",
}


@dataclass(frozen=True)
class TrainingDraws:
    """The variants a training may have seen: the evaluation's must differ from them.

    ``data_*``: ``data.variants`` (the manifest in ``data_dir``, else ``data_count *
    data_tries`` candidates of its seed stream); ``dagger_*``: DAgger's fresh variants per
    plant and round (none: an empty range), drawn with the data's range and tries.
    """

    data_dir: Path
    data_seed: int
    data_range: float
    data_count: int
    data_tries: int
    dagger_seeds: range
    dagger_fresh: int


def _candidates(
    plant: Plant, seeds: Sequence[int], default_range: float, n: int
) -> list[dict[str, float]]:
    """The first ``n`` candidates of each seed's stream (:func:`candidate_factors`)."""
    return [
        f for s in seeds for f in itertools.islice(candidate_factors(plant, s, default_range), n)
    ]


def _training_factors(
    plants: Sequence[Plant], training: TrainingDraws
) -> tuple[str, dict[str, list[dict[str, float]]]]:
    """The training variants' factors and where they came from (:class:`TrainingDraws`)."""
    manifest = training.data_dir / "manifest.json"
    recorded = read_manifest(training.data_dir).get("variants") if manifest.is_file() else None
    if recorded:  # the manifest is checked against its digest
        source = f"manifest {manifest}"
        out = {name: [v["factors"] for v in rec["kept"]] for name, rec in recorded.items()}
    else:
        n = training.data_count * training.data_tries  # every candidate the data may have drawn
        source = f"seed stream data.variants.seed={training.data_seed}"
        out = {p.name: _candidates(p, [training.data_seed], training.data_range, n)
               for p in plants}  # fmt: skip
    seeds = training.dagger_seeds
    if training.dagger_fresh and seeds:
        source += f" and DAgger's fresh variants (seeds {seeds.start}..{seeds.stop - 1})"
        n = training.dagger_fresh * training.data_tries
        for p in plants:
            out[p.name] = out.get(p.name, []) + _candidates(p, seeds, training.data_range, n)
    return source, out


def check_disjoint(
    draws: Mapping[str, VariantDraw],
    plants: Sequence[Plant],
    training: TrainingDraws,
    seed: int,
    key: str = "evaluation.variants.seed",
) -> dict[str, Any]:
    """Refuse evaluation variants equal to a training variant; return what was checked.

    ``seed``: the evaluation's (``key`` names it in the messages).

    Raises
    ------
    ValueError
        The seed is the data's or one of DAgger's, or a drawn factor vector equals a
        training one.
    """
    if seed == training.data_seed:
        raise ValueError(
            f"{key} = {seed} is data.variants.seed: choose another, so the evaluation's "
            "variants are not the training's"
        )
    seeds = training.dagger_seeds
    if training.dagger_fresh and seed in seeds:
        raise ValueError(
            f"{key} = {seed} is one of DAgger's fresh-variant seeds "
            f"({seeds.start}..{seeds.stop - 1}): choose another, or move "
            "dagger.sampler.variants.seed"
        )
    source, train = _training_factors(plants, training)
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
        chosen = [v for v in variants if runs_on(spec, v.plant.name)]
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


def _judge(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    spec: VariantEvalSettings,
    scenarios: Mapping[str, Mapping[str, Any]],
    training: TrainingDraws,
    draw: tuple[int, int, str],
) -> tuple[dict[str, VariantDraw], pd.DataFrame, dict[str, Any]]:
    """The ``draw`` (seed, count, its key), metrics and summary (the bars judge the first)."""
    seed, count, key = draw
    first = next(iter(scenarios.values()))
    steps = int(round(float(first["duration"]) / plants[0].dt))
    draws = {
        p.name: sample_variants(p, count, seed, spec.range, (1.0, -1.0), steps, spec.max_tries)
        for p in plants
    }
    disjoint = check_disjoint(draws, plants, training, seed, key)
    df = evaluate_variants(runtime, draws, scenarios)
    summary = summarise_variants(df, next(iter(scenarios)), spec.bar)
    summary["disjoint"] = disjoint
    return draws, df, summary


def run_variants(
    settings: EvaluationSettings,
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    training: TrainingDraws,
    out_dir: Path,
    record: Record,
    run: EvalRun | None = None,
) -> dict[str, Any]:
    """Draw, check, evaluate and write the variants report to ``out_dir``; its summary."""
    check_reports_dir(out_dir, OWNED)
    spec = settings.variants
    scen = {n: settings.scenarios[n] for n in spec.scenarios}
    test = (spec.seed, spec.count, "evaluation.variants.seed")
    draws, df, summary = _judge(runtime, plants, spec, scen, training, test)
    summary["rejected"] = {n: d.rejected for n, d in draws.items() if d.rejected}
    val, held_out = None, spec.validation
    if held_out is not None:  # the held-out check: the judged scenario on a second draw
        judged = {spec.scenarios[0]: scen[spec.scenarios[0]]}
        draw = (held_out.seed, held_out.count, "evaluation.variants.validation.seed")
        _, val, held = _judge(runtime, plants, spec, judged, training, draw)
        summary["validation"] = {**held, "seed": held_out.seed, "count": held_out.count}
    setpoint = None
    if settings.setpoint is not None and runtime.integral:  # the nominal plants' set points
        check = settings.setpoint  # its holds alone, in one loop in this process
        setpoint = run_suite(
            runtime, plants, {}, setpoint=check, progress=False, processes=1
        ).setpoint
    if setpoint is not None:
        summary["setpoint"] = setpoint_summary(setpoint)
    summary.update(record["summary"])
    with publish_snapshot(out_dir, OWNED, run) as (staging, logged):
        logged.update(summary)
        df.to_csv(staging / "metrics.csv", index=False)
        if setpoint is not None:
            setpoint.to_csv(staging / "setpoint.csv", index=False)
        if val is not None:
            val.to_csv(staging / "validation.csv", index=False)
        _variants_table(draws).to_csv(staging / "variants.csv", index=False)
        write_json(staging / "summary.json", summary)
        write_json(staging / "provenance.json", record["provenance"])
        if settings.plots:
            plot_variants(df, spec.scenarios[0], staging / "plots")
    return summary
