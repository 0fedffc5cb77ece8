"""The held-out protocol's zero-shot routes and its held-out family draw (issue 50).

The model card route meets each held-out plant by its model, the in-context route by a
normaliser row of its demonstrations' RMS; :func:`judge_routes` holds issue 50's bars.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import numpy as np
import pandas as pd
import torch
from omegaconf import OmegaConf

from generalist_control.common.paths import conf_dir
from generalist_control.data.generation import generate_demos
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.runner import evaluate
from generalist_control.model.bank import add_scales, plant_scales
from generalist_control.model.policy import Policy, load_policy
from generalist_control.plants.definition import Plant
from generalist_control.simulation.family_draw import draw_family, read_families

__all__ = [
    "ROUTES",
    "ROUTES_BAR",
    "family_draw",
    "judge_routes",
    "ratio",
    "zero_shot",
]

log = logging.getLogger(__name__)

#: The zero-shot routes, each its training's folder under ``unseen.models``.
ROUTES = {"card": "family_card", "in_context": "family_context"}

#: Issue 50's bars (``unseen.routes_bar`` overrides them; docs/pipeline.md).
ROUTES_BAR = {"near": 1.10, "all": 1.25, "allowed_over": 1, "median": 1.05, "p95": 1.25,
              "context": 1.25}  # fmt: skip


def _scales(
    policy: Policy, meta: Mapping[str, Any], plant: Plant, data: Mapping[str, Any]
) -> dict[str, torch.Tensor]:
    """The plant's normaliser row: the RMS of its demonstrations' windows."""
    demos = generate_demos([plant], data, progress=False)
    channels = policy.channels
    w = demos.windows(
        int(meta["history"]), int(meta["horizon"]),
        "integral" in channels, "previous_control" in channels,
    )  # fmt: skip
    state, mask, ref, target = (
        torch.from_numpy(np.asarray(getattr(w, k))) for k in ("state", "mask", "ref", "target")
    )
    return plant_scales(state, mask, ref, target, policy.normaliser.mapped)


def zero_shot(
    route: str, path: Path, plant: Plant, data: Mapping[str, Any]
) -> tuple[Policy, dict[str, Any]]:
    """The route's policy meeting ``plant`` with nothing learned, and its meta."""
    policy, meta = load_policy(path)
    if route == "card":
        rt = PolicyRuntime(policy, meta)
        rt.add_plant(plant)
        grown = rt.policy
    else:
        grown = add_scales(policy, _scales(policy, meta, plant, data))
    tags = {**meta["tags"], plant.name: grown.net.n_tags - 1}
    outputs = {**meta.get("outputs", {}), plant.name: [float(c) for c in plant.C[0]]}
    orders = {**meta["orders"], plant.name: plant.order}
    return grown, {**meta, "tags": tags, "orders": orders, "outputs": outputs}


def _family_node(spec: Mapping[str, Any], data: Mapping[str, Any]) -> dict[str, Any]:
    """``conf/families/<family>.yaml`` at ``spec.seed``, ``spec.checks`` (if any) merged in."""
    node = OmegaConf.merge(
        {"data": dict(data)},
        {"f": OmegaConf.load(conf_dir() / "families" / f"{spec['family']}.yaml")},
        {"f": {"generator": {"seed": int(spec["seed"])}, "checks": spec["checks"] or {}}},
    )
    return cast(
        dict[str, Any], cast(dict[str, Any], OmegaConf.to_container(node, resolve=True))["f"]
    )


def family_draw(
    path: Path,
    spec: Mapping[str, Any],
    data: Mapping[str, Any],
    scenarios: Mapping[str, Mapping[str, Any]],
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The card route on ``spec.count`` plants of family ``spec.family`` drawn from ``spec.seed``.

    Returns the long-form metrics of every scenario (``policy`` ``card``) and their summary.

    Raises
    ------
    ValueError
        If ``spec.seed`` is the seed of a family the policy was trained on.
    """
    policy, meta = load_policy(path)
    seeds = {int(f["seed"]) for f in meta.get("families", []) if f["name"] == spec["family"]}
    if int(spec["seed"]) in seeds:
        raise ValueError(
            f"unseen.family_draw.seed {spec['seed']} drew the policy's training family "
            f"(seeds {sorted(seeds)}): choose a seed no training used"
        )
    family, settings = read_families(_family_node(spec, data))
    draw = draw_family(family, int(spec["count"]), settings.checks)
    rt = PolicyRuntime(policy, meta)
    for p in draw.plants:
        rt.add_plant(p)
    df, _ = evaluate(rt, draw.plants, scenarios)
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
    """Issue 50's bars (:data:`ROUTES_BAR`) on the routes' figures; ``pass`` of each."""
    b = {**ROUTES_BAR, **bar}
    card = {n: e["policies"]["card"] for n, e in entries.items()}
    worst = {n: max(ratio(f["ISE_ratio"]), ratio(f["RMSE_ratio_worst"])) for n, f in card.items()}
    over = sorted(n for n, v in worst.items() if v > b["near"])
    ctx = {n: e["policies"]["in_context"] for n, e in entries.items()}
    ctx_over = sorted(n for n, f in ctx.items() if ratio(f["ISE_ratio"]) > b["context"])
    bars = {
        "card_no_divergence": sum(int(f["diverged_runs"]) for f in card.values()) == 0,
        "card_most_within": len(over) <= int(b["allowed_over"]),
        "card_all_within": all(v <= b["all"] for v in worst.values()),
        "context_no_divergence": sum(int(f["diverged_runs"]) for f in ctx.values()) == 0,
        "context_most_within": len(ctx_over) <= int(b["allowed_over"]),
    }
    if draw is not None:
        bars["draw_no_divergence"] = draw["diverged_runs"] == 0
        bars["draw_median"] = draw["ISE_ratio"]["median"] <= b["median"]
        bars["draw_p95"] = draw["ISE_ratio"]["p95"] <= b["p95"]
    return {"bars": bars, "card_over": over, "context_over": ctx_over,
            "pass": all(bars.values())}  # fmt: skip
