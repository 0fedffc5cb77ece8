"""The tag-free stage's analyses: ``python -m analysis.run_tag_free experiment=tag_free``.

Research, not product: the package :mod:`generalist_control` never imports ``analysis``.
After the stage's evaluation (``reports/tag_free/metrics.csv``), this writes the tag-free bar
and its diagnostics to ``reports/tag_free_bar`` (:func:`analysis.tag_free.write_tag_free_report`):
how soon the history tells plants apart, when diverged runs left their expert (the
evaluation's scenarios are run again only if any GC run diverged), whether the expert
making the first controls saves a missed plant, the policy's local gains beside LQI's, and
what its identity head names along the expert's and its own closed loop.

Settings beyond the composed config: ``+analysis.out=<dir>``, ``+analysis.handover=[...]``
(samples the expert makes first), ``+analysis.gain_samples=<n>``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import DictConfig

from analysis.handover import handover_table
from analysis.identity import identity_trace
from analysis.local_gains import local_gains
from analysis.tag_free import write_tag_free_report
from generalist_control.common.sections import as_dict
from generalist_control.common.stage_main import stage_main
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.eval_config import read_evaluation
from generalist_control.evaluation.runner import evaluate
from generalist_control.model.plant import InferredPlant
from generalist_control.model.policy import POLICY_FILE, load_policy
from generalist_control.plants.catalog import plants_from_config

__all__ = ["main", "run"]

log = logging.getLogger(__name__)

#: Defaults of ``+analysis.*``.
DEFAULTS: dict[str, Any] = {
    "out": "reports/tag_free_bar",
    "handover": [0, 1, 2, 5, 10, 20, 40],
    "gain_samples": 40,
}


def run(cfg: DictConfig) -> dict[str, Any]:
    """Write the tag-free report of the policy ``cfg`` names; return its bar."""
    opts = {**DEFAULTS, **as_dict(cfg.get("analysis") or {})}
    source = cfg.get("policy") or str(Path(cfg.paths.models_dir) / POLICY_FILE)
    policy, meta = load_policy(source)
    settings = read_evaluation(as_dict(cfg.evaluation))
    runtime = PolicyRuntime(policy, meta, backend=settings.backend)
    metrics = Path(cfg.paths.reports_dir) / "metrics.csv"
    if not metrics.is_file():
        raise FileNotFoundError(
            f"no evaluation at {metrics}: run python -m generalist_control.evaluate with the "
            "same config first"
        )
    df = pd.read_csv(metrics)
    plants = [p for p in plants_from_config(as_dict(cfg.systems)) if p.name in set(df.system)]
    scenarios = settings.scenarios
    trajectories: dict = {}  # no diverged run: an empty departures table
    gc = df[(df.controller == "GC") & (df.metric == "diverged")]
    if (gc.value > 0).any():  # when each diverged run left its expert
        _, trajectories = evaluate(runtime, plants, scenarios, settings.crazyflie)
    step = scenarios["step"]
    after = int(opts["gain_samples"])
    trace = None
    if isinstance(policy.net.plant, InferredPlant):
        trace = identity_trace(runtime, plants, step, [0, after])
    verdict = write_tag_free_report(
        df,
        policy,
        plants,
        opts["out"],
        trajectories=trajectories,
        handover=handover_table(runtime, plants, step, [int(n) for n in opts["handover"]]),
        gains=local_gains(runtime, plants, step, after),
        identity_trace=trace,
    )
    log.info("tag-free bar written to %s: %s", opts["out"], json.dumps({"met": verdict["met"]}))
    return verdict


@stage_main("config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the tag-free analyses."""
    run(cfg)


if __name__ == "__main__":
    main()
