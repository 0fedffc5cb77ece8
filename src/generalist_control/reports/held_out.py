"""The held-out protocol (``beyond/dvc.yaml:unseen``): plants the policy has never seen.

Per held-out plant the :data:`POLICIES` (and ``unseen.routes``: the model card route, with a
held-out family draw) run every scenario against its LQI; then the bars (:func:`judge`,
:func:`judge_routes`; in context is the tag-free ``zero_shot``). docs/pipeline.md has the files.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from contextlib import nullcontext
from pathlib import Path
from typing import Any, cast

import mlflow
import numpy as np
import pandas as pd
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from generalist_control.adaptation import adapt
from generalist_control.adaptation.job import learn, prepare
from generalist_control.adaptation.request import AdaptRequest
from generalist_control.common.atomic import (
    check_replaceable,
    publish_directory,
    staging_directory,
)
from generalist_control.common.jsonsafe import write_json
from generalist_control.common.paths import conf_dir
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.eval_config import EvaluationSettings
from generalist_control.evaluation.eval_run import provenance
from generalist_control.evaluation.runner import evaluate
from generalist_control.evaluation.summary import summarise
from generalist_control.model.policy import POLICY_FILE, Policy, load_policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.definition import Plant
from generalist_control.reports.explore import plant_class
from generalist_control.simulation.family_draw import draw_family, read_families
from generalist_control.simulation.scenarios import with_state_draw
from generalist_control.tracking import mlflow_utils
from generalist_control.training.unseen_draw import UnseenDraw

__all__ = [
    "OWNED",
    "POLICIES",
    "ROUTES",
    "UnseenSettings",
    "card_met",
    "family_draw",
    "judge",
    "judge_routes",
    "ratio",
    "run_unseen",
]

log = logging.getLogger(__name__)

#: The policies compared on each held-out plant, in the report's order.
POLICIES = ("adapted", "zero_shot", "trained_with")

#: What ``reports/unseen`` holds: the only entries the stage may replace.
OWNED: dict[str, str | None] = {"metrics.csv": None, "summary.json": None}


@dataclasses.dataclass(frozen=True)
class UnseenSettings:
    """What the stage reads of its config (``conf/unseen.yaml``), read once by the entry point."""

    reports_dir: Path
    models: Path
    trained_with: Path
    routes: tuple[str, ...]  #: the :data:`ROUTES` evaluated
    family_draw: Mapping[str, Any] | None
    bar: Mapping[str, Any]
    routes_bar: Mapping[str, Any]
    evaluation: EvaluationSettings
    data: Mapping[str, Any]
    logger: Mapping[str, Any]


#: The stage's trainings: ``<unseen.models>/<folder>/policy.ckpt``.
TRAININGS = {"adapted": "default", "zero_shot": "tag_free"}

#: How each training is made (quoted when one is missing).
STAGE = "dvc repro beyond/dvc.yaml:unseen (its first two commands train them)"
FAMILY_STAGE = "dvc repro beyond/dvc.yaml:unseen (its family commands train them)"


def judge(entries: Mapping[str, Any], bar: Mapping[str, Any]) -> dict[str, Any]:
    """The bars ``bar`` (``unseen.bar``) on the ``adapted`` figures, each with ``pass``."""
    figs = {name: e["policies"]["adapted"] for name, e in entries.items()}
    ise = {n: ratio(f["ISE_ratio"]) for n, f in figs.items()}
    rmse = {n: ratio(f["RMSE_ratio_worst"]) for n, f in figs.items()}
    over = sorted(n for n in figs if ise[n] > bar["ISE_ratio"] or rmse[n] > bar["RMSE_ratio"])
    worst = max([*ise.values(), *rmse.values()], default=float("nan"))
    diverged = sum(int(f["diverged_runs"]) for f in figs.values())
    wall = max((float(e["adaptation_wall_s"]) for e in entries.values()), default=0.0)
    allowed = int(bar["allowed_over"])

    def at_most(value: float, limit: float) -> dict[str, Any]:
        return {"value": value, "limit": limit, "pass": value <= limit}

    bars = {
        "no_divergence": {"GC_diverged_runs": diverged, "pass": diverged == 0},
        "adaptation_wall_s": at_most(wall, bar["wall_s"]),
        "most_within": {
            "plants_over": len(over),
            "over": over,
            "allowed_over": allowed,
            "pass": len(over) <= allowed,
        },
        "all_within": at_most(worst, bar["all_ratio"]),
    }
    return {"bars": bars, "pass": all(v["pass"] for v in bars.values())}


def _paths(settings: UnseenSettings) -> tuple[dict[str, Path], dict[str, Path]]:
    """The three policies' files and those of ``unseen.routes``, checked to exist."""
    made = {k: (settings.models / v / POLICY_FILE, STAGE) for k, v in TRAININGS.items()}
    made["trained_with"] = (settings.trained_with, "dvc repro train (the pipeline's policy)")
    made.update(
        {k: (settings.models / ROUTES[k] / POLICY_FILE, FAMILY_STAGE) for k in settings.routes}
    )
    for key, (path, make) in made.items():
        if not path.is_file():
            raise FileNotFoundError(f"no {key} policy at {path}; make it with: {make}")
    paths = {k: path for k, (path, _) in made.items()}
    return {k: paths[k] for k in POLICIES}, {k: paths[k] for k in ROUTES if k in paths}


def _tag_free(request: AdaptRequest, path: Path) -> tuple[Policy, dict[str, Any]]:
    """The tag-free policy named for the plant (its scales only); nothing written."""
    named = dataclasses.replace(request, adapt=dataclasses.replace(request.adapt, learn=False))
    policy, meta, _ = learn(prepare(dataclasses.replace(named, policy=str(path))))
    return policy, meta


def _evaluated(
    settings: EvaluationSettings, label: str, policy: Policy, meta: dict[str, Any], plant: Plant
) -> pd.DataFrame:
    """Every scenario on ``plant``: GC (this policy), LQI and LQI-AW; a ``policy`` column."""
    runtime = PolicyRuntime(policy, meta, backend=settings.backend)
    df, _ = evaluate(runtime, [plant], settings.scenarios, settings.crazyflie)
    df.insert(0, "policy", label)
    return df


def _figures(df: pd.DataFrame) -> dict[str, Any]:
    """One plant and policy: GC's divergences and its worst ratios to LQI (the summary's)."""
    s = summarise(df)
    step = s["ratios"].get("step", {})
    rmse = [v["worst_RMSE_ratio"] for v in s["tracking"].values()]
    ess = [v["worst_relative_ess_GC"] for v in s["ratios"].values()]
    return {
        "diverged_runs": int(sum(sum(v.values()) for k, v in s["diverged"].items() if "GC" in k)),
        "ISE_ratio": step.get("worst_ISE_ratio"),
        "ITAE_ratio": step.get("worst_ITAE_ratio"),
        "RMSE_ratio_worst": max(rmse) if rmse else None,
        "relative_ess_worst": max(ess) if ess else None,
        "ratios": s["ratios"],
        "tracking": s["tracking"],
    }


def _plant(
    settings: UnseenSettings,
    request: AdaptRequest,
    paths: Mapping[str, Path],
    routes: Mapping[str, Path],
) -> tuple[pd.DataFrame, dict]:
    """Adapt, name and load the policies for one plant (and the zero-shot routes'); evaluate."""
    name = request.plant
    record, objects = adapt(dataclasses.replace(request, policy=str(paths["adapted"])))
    policies = {
        "adapted": (objects["policy"], objects["meta"]),
        "zero_shot": _tag_free(request, paths["zero_shot"]),
        "trained_with": load_policy(paths["trained_with"]),
    }
    plant = load_plant(name)
    policies.update({k: card_met(path, plant) for k, path in routes.items()})
    frames = [_evaluated(settings.evaluation, k, p, m, plant) for k, (p, m) in policies.items()]
    df = pd.concat(frames, ignore_index=True)
    entry = {
        "class": plant_class(plant),
        "demonstrations": record["demonstrations"],
        "adaptation_wall_s": record["wall_s"],
        "adaptation": {k: record[k] for k in ("init", "closed_loop", "learned")},
        "adapted_policy": str(objects["policy_path"]),
        "policies": {k: _figures(df[df.policy == k]) for k in policies},
    }
    return df, entry


#: The zero-shot routes trained apart, each its training's folder under ``unseen.models``;
#: the in-context route is the tag-free policy, ``zero_shot`` (always evaluated).
ROUTES = {"card": "family_card"}


def card_met(path: Path, plant: Plant) -> tuple[Policy, dict[str, Any]]:
    """The card policy at ``path`` meeting ``plant``: its row from the plant's model.

    (Not the ``zero_shot`` policy: that is the tag-free one, the in-context route.)
    """
    policy, meta = load_policy(path)
    return UnseenDraw.of([dataclasses.replace(plant, tag=0)], policy).met(policy, meta)


def _family_node(spec: Mapping[str, Any], data: Mapping[str, Any]) -> dict[str, Any]:
    """``conf/families/<family>.yaml`` (composed) at ``spec.seed``, ``spec.checks`` merged in."""
    inside = GlobalHydra.instance().is_initialized()  # in a stage: the stage's search path
    with nullcontext() if inside else initialize_config_dir(str(conf_dir()), version_base="1.3"):
        family = compose(f"families/{spec['family']}").families
    node = OmegaConf.merge(
        {"data": dict(data)},
        {"f": family},
        {"f": {"generator": {"seed": int(spec["seed"])}, "checks": spec["checks"] or {}}},
    )
    tree = cast(dict[str, Any], OmegaConf.to_container(node, resolve=True))
    return cast(dict[str, Any], tree["f"])


def family_draw(
    path: Path,
    spec: Mapping[str, Any],
    data: Mapping[str, Any],
    scenarios: Mapping[str, Mapping[str, Any]],
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The card route's metrics (``policy`` ``card``) and summary on a draw of ``spec.family``.

    Raises
    ------
    ValueError
        If ``spec.seed`` is the seed of a family the policy was trained or validated on.
    """
    policy, meta = load_policy(path)
    seeds = {int(f["seed"]) for f in meta.get("families", []) if f["name"] == spec["family"]}
    if int(spec["seed"]) in seeds:
        raise ValueError(
            f"unseen.family_draw.seed {spec['seed']} drew a family the policy was trained or "
            f"validated on (seeds {sorted(seeds)}): choose a seed no training used"
        )
    family, settings = read_families(_family_node(spec, data))
    draw = draw_family(family, int(spec["count"]), settings.checks)
    rt = PolicyRuntime(*UnseenDraw(tuple(draw.plants)).met(policy, meta))
    df, _ = evaluate(rt, draw.plants, with_state_draw(scenarios, spec["state_draw"]))
    df.insert(0, "policy", "card")
    return df, _draw_summary(df, draw.plants, spec)


def _draw_summary(df: pd.DataFrame, plants: list[Plant], spec: Mapping[str, Any]) -> dict:
    gc = df[df.controller == "GC"]
    step = df[(df.scenario == "step") & (df.metric == "ISE")]
    ise = step.pivot_table(index="system", columns="controller", values="value")
    ratio = (ise["GC"] / ise["LQI"]).reindex([p.name for p in plants])
    diverged = gc[gc.metric == "diverged"].groupby("system").value.sum()
    ratio[diverged.reindex(ratio.index).fillna(0) > 0] = np.inf
    finite = ratio.replace(np.inf, np.nan)
    worst = ratio.sort_values(ascending=False).head(5)
    what = {p.name: p.description for p in plants}
    return {
        "family": spec["family"], "seed": int(spec["seed"]), "plants": len(plants),
        "diverged_plants": int((diverged > 0).sum()),
        "diverged_runs": int(diverged.sum()),
        "ISE_ratio": {"median": _quantile(ratio, 0.5), "p95": _quantile(ratio, 0.95),
                      "max": float(ratio.max()), "min": float(finite.min())},
        "worst": [{"plant": n, "ISE_ratio": float(v), "plant_is": what[n]}
                  for n, v in worst.items()],
        "ISE_ratios": {n: float(v) for n, v in ratio.items()},
    }  # fmt: skip


def _quantile(values: pd.Series, q: float) -> float:
    """The ``q`` quantile, a sample of the data (a diverged plant's ``inf`` counts as worst)."""
    return float(np.quantile(values.to_numpy(dtype=float), q, method="inverted_cdf"))


def ratio(value: Any) -> float:
    """A ratio of a summary; a missing one (every run diverged) counts as infinite."""
    return float("inf") if value is None else float(value)


def judge_routes(
    entries: Mapping[str, Any], draw: Mapping[str, Any] | None, bar: Mapping[str, Any]
) -> dict[str, Any]:
    """Issue 50's bars (``unseen.routes_bar``); the card route not evaluated: ``not_run`` (fails).

    In context: the tag-free policy (``zero_shot``), which reads the plant from its window.
    """
    card, ctx = ({n: e["policies"][k] for n, e in entries.items() if k in e["policies"]}
                 for k in ("card", "zero_shot"))  # fmt: skip
    worst = {n: max(ratio(f["ISE_ratio"]), ratio(f["RMSE_ratio_worst"])) for n, f in card.items()}
    over = sorted(n for n, v in worst.items() if v > bar["near"])
    ctx_over = sorted(n for n, f in ctx.items() if ratio(f["ISE_ratio"]) > bar["context"])
    bars: dict[str, bool] = {}
    if card:
        bars["card_no_divergence"] = sum(int(f["diverged_runs"]) for f in card.values()) == 0
        bars["card_most_within"] = len(over) <= int(bar["allowed_over"])
        bars["card_all_within"] = all(v <= bar["all"] for v in worst.values())
    if ctx:
        bars["context_no_divergence"] = sum(int(f["diverged_runs"]) for f in ctx.values()) == 0
        bars["context_most_within"] = len(ctx_over) <= int(bar["allowed_over"])
    if draw is not None:
        bars["draw_no_divergence"] = draw["diverged_runs"] == 0
        bars["draw_median"] = draw["ISE_ratio"]["median"] <= bar["median"]
        bars["draw_p95"] = draw["ISE_ratio"]["p95"] <= bar["p95"]
    not_run = [] if card else ["card"]
    return {"bars": bars, "card_over": over, "context_over": ctx_over, "not_run": not_run,
            "pass": all(bars.values()) and not not_run}  # fmt: skip


def _log(logger: Mapping[str, Any], summary: Mapping[str, Any], out_dir: Path) -> None:
    """The stage's own run (experiment ``<prefix>/unseen``)."""
    flat = {}
    for name, entry in summary["held_out"].items():
        flat[f"unseen/{name}/adaptation_wall_s"] = entry["adaptation_wall_s"]
        for label, fig in entry["policies"].items():
            for key in ("ISE_ratio", "ITAE_ratio", "RMSE_ratio_worst", "diverged_runs"):
                if fig[key] is not None and np.isfinite(fig[key]):
                    flat[f"unseen/{name}/{label}/{key}"] = float(fig[key])
    with mlflow_utils.mlflow_run({**logger, "run_name": "unseen"}, kind="unseen"):
        mlflow.log_params({"held_out": ",".join(summary["held_out"])})
        mlflow.log_metrics(flat)
        mlflow.log_artifacts(str(out_dir), "unseen")


def run_unseen(settings: UnseenSettings, requests: Mapping[str, AdaptRequest]) -> dict[str, Any]:
    """Adapt to, and evaluate on, every held-out plant; write ``paths.reports_dir``.

    Raises
    ------
    FileNotFoundError
        If one of the three policies is missing (with the command that makes it).
    generalist_control.common.atomic.ForeignDirectoryError
        If the reports folder holds files the stage does not write.
    """
    out_dir = settings.reports_dir
    check_replaceable(out_dir, OWNED, "paths.reports_dir")
    paths, routes = _paths(settings)
    frames, entries = [], {}
    for name, request in requests.items():
        df, entries[name] = _plant(settings, request, paths, routes)
        frames.append(df)
        log.info("held-out plant %s: adapted in %.0f s", name, entries[name]["adaptation_wall_s"])
    summary = {
        "held_out": entries,
        **judge(entries, settings.bar),
        "policies": {k: str(v) for k, v in {**paths, **routes}.items()},
        "provenance": provenance(),
    }
    draw = None
    if settings.family_draw is not None and "card" in routes:
        spec, scenarios = settings.family_draw, settings.evaluation.scenarios
        df, draw = family_draw(routes["card"], spec, settings.data, scenarios)
        frames.append(df)
        log.info("held-out family draw: median ISE ratio %.4g", draw["ISE_ratio"]["median"])
    summary["routes"] = judge_routes(entries, draw, settings.routes_bar)
    summary["family_draw"] = draw
    with staging_directory(out_dir) as staging:
        pd.concat(frames, ignore_index=True).to_csv(staging / "metrics.csv", index=False)
        write_json(staging / "summary.json", summary)
        publish_directory(staging, out_dir, OWNED, "paths.reports_dir")
    _log(settings.logger, summary, out_dir)
    return summary
