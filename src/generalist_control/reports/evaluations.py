"""The ablation points' evaluations: verdicts, per-scenario scores, what separates the points.

Each evaluation folder is matched to the run that trained its policy (:func:`match`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.common.jsonsafe import finite
from generalist_control.reports.runs import ByConfig, RunPoint, run_label

__all__ = [
    "Evaluation",
    "load_evaluations",
    "match",
    "points_frame",
    "scenario_scores",
    "scenario_worst",
    "separating",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Evaluation:
    """One evaluation folder: its ``summary.json`` and, if there, its ``metrics.csv``."""

    path: Path
    summary: Mapping[str, Any]
    metrics: pd.DataFrame | None


def load_evaluations(directory: str | Path | None) -> list[Evaluation]:
    """The evaluations under ``directory`` (``*/summary.json``), oldest first; none if absent."""
    if directory is None or not Path(directory).is_dir():
        return []
    out = []
    for file in sorted(Path(directory).glob("*/summary.json"), key=lambda f: f.stat().st_mtime):
        csv = file.with_name("metrics.csv")
        metrics = pd.read_csv(csv) if csv.is_file() else None
        out.append(Evaluation(file.parent, json.loads(file.read_text()), metrics))
    return out


def match(evaluations: Sequence[Evaluation], runs: Sequence[RunPoint]) -> dict[str, Evaluation]:
    """Each run's evaluation, by run id (the newest of several).

    An evaluation is a run's when it names the run (``policy.mlflow_run_id``) or evaluated
    the policy the run wrote (``policy.source`` in its ``policy_dir``, from the working folder).
    """
    out: dict[str, Evaluation] = {}
    for ev in evaluations:  # oldest first: the newest wins
        policy = ev.summary.get("policy") or {}
        folder = str(Path(str(policy.get("source") or "")).resolve().parent)
        for p in runs:
            if policy.get("mlflow_run_id") == p.run_id or (
                not policy.get("mlflow_run_id") and folder == p.policy_dir
            ):
                out[p.run_id] = ev
    for p in runs:
        if p.run_id not in out and evaluations:
            log.warning("no evaluation of run %s (%s) found", p.run_name, p.run_id)
    return out


def scenario_scores(
    labels: Mapping[str, str], evaluations: Mapping[str, Evaluation]
) -> pd.DataFrame:
    """Per run, scenario and plant: GC's mean ISE (step) or RMSE (tracking) over LQI's.

    ``labels``: run id -> its label, in table order. Columns ``run, run_id, scenario, kind,
    plant, metric, GC, LQI, ratio, GC_diverged``, from each run's ``metrics.csv``.
    """
    cols = ["run", "run_id", "scenario", "kind", "plant", "metric", "GC", "LQI", "ratio"]
    frames = []
    for run_id, label in labels.items():
        ev = evaluations.get(run_id)
        if ev is None or ev.metrics is None:
            continue
        df = ev.metrics
        step = df.groupby("scenario", sort=False)["metric"].agg(lambda m: "rise_time" in set(m))
        kinds = step.map({True: "step", False: "tracking"})
        metric = kinds.map({"step": "ISE", "tracking": "RMSE"})
        wanted = df[df["metric"] == df["scenario"].map(metric)]
        means = wanted.groupby(["scenario", "system", "controller"], sort=False)["value"].mean()
        table = means.unstack("controller")
        if not {"GC", "LQI"} <= set(table.columns):
            continue
        diverged = df[(df["metric"] == "diverged") & (df["controller"] == "GC")]
        div = diverged.groupby(["scenario", "system"])["value"].sum()
        part = table[["GC", "LQI"]].reset_index().rename(columns={"system": "plant"})
        part["ratio"] = part["GC"] / part["LQI"]
        part["kind"] = part["scenario"].map(kinds)
        part["metric"] = part["scenario"].map(metric)
        keys = list(zip(part["scenario"], part["plant"], strict=True))
        part["GC_diverged"] = [int(div.get(k, 0)) for k in keys]
        part.insert(0, "run_id", run_id)
        part.insert(0, "run", label)
        frames.append(part)
    if not frames:
        return pd.DataFrame(columns=[*cols, "GC_diverged"])
    return pd.concat(frames, ignore_index=True)[[*cols, "GC_diverged"]]


def scenario_worst(
    labels: Mapping[str, str], evaluations: Mapping[str, Evaluation]
) -> pd.DataFrame:
    """Per run and scenario, from ``summary.json``: the worst plant's ratio, GC's divergences.

    Columns ``run, run_id, scenario, kind, worst_ratio`` (ISE or RMSE; inf: all diverged),
    ``worst_plant, GC_diverged``.
    """
    rows = []
    for run_id, label in labels.items():
        ev = evaluations.get(run_id)
        if ev is None:
            continue
        s = ev.summary
        diverged = (s.get("diverged") or {}).get("GC") or {}
        kinds = [
            ("step", "ISE", s.get("ratios") or {}),
            ("tracking", "RMSE", s.get("tracking") or {}),
        ]
        for kind, metric, by_scen in kinds:
            for scen, fig in by_scen.items():
                value = fig.get(f"worst_{metric}_ratio")
                rows.append(
                    (label, run_id, scen, kind, float("inf") if value is None else float(value),
                     fig.get(f"worst_{metric}_system"), int(diverged.get(scen, 0)))
                )  # fmt: skip
    cols = ["run", "run_id", "scenario", "kind", "worst_ratio", "worst_plant", "GC_diverged"]
    return pd.DataFrame(rows, columns=cols)


def separating(worst: pd.DataFrame, bar: Mapping[str, Any]) -> dict[str, str]:
    """Scenario -> why it separates the runs, in the order the scenarios first appear.

    GC diverges in it for some runs only, or its worst ratio is within ``bar``'s limit
    (``ISE_ratio`` for step scenarios, ``RMSE_ratio`` for tracking ones) for some runs only.
    """
    out: dict[str, str] = {}
    for scen, part in worst.groupby("scenario", sort=False):
        if len(part) < 2:
            continue
        runs = list(part["run"])
        div = part["GC_diverged"] > 0
        if div.any() and not div.all():
            out[str(scen)] = "GC diverges for " + ", ".join(np.array(runs)[div.to_numpy()])
            continue
        limit = float(bar["ISE_ratio" if part["kind"].iloc[0] == "step" else "RMSE_ratio"])
        within = part["worst_ratio"] <= limit
        if within.any() and not within.all():
            beyond = ", ".join(np.array(runs)[~within.to_numpy()])
            out[str(scen)] = f"worst ratio beyond {limit:g} for {beyond} only"
    return out


def points_frame(
    by_config: ByConfig,
    plants: Sequence[str],
    evaluations: Mapping[str, Evaluation],
) -> pd.DataFrame:
    """One row per run (``points.csv``): its point, seed, figures and its evaluation's verdicts."""
    rows = []
    for (d, m), runs in sorted(by_config.items()):
        for p in runs:
            scores = [p.mse[k] for k in plants if k in p.mse]
            row: dict[str, Any] = {
                "run": run_label(p),
                "d": d,
                "M": m,
                "seed": p.seed,
                "run_id": p.run_id,
                "n_parameters": p.n_parameters,
                "final_train_loss": finite(p.train_loss),
                "final_val_loss": finite(p.val_loss),
                "best_val_loss": finite(p.best_val_loss),
                "mse_mean": float(np.mean(scores)) if scores else None,
                **{f"mse/{k}": p.mse.get(k) for k in plants},
                "closed_loop_diverged": p.diverged,
            }
            ev = evaluations.get(p.run_id)
            if ev is not None:
                verdicts = (ev.summary.get("quality_bar") or {}).items()
                bar = {str(k): (None if v is None else bool(v)) for k, v in verdicts}
                diverged = (ev.summary.get("diverged") or {}).get("GC") or {}
                row["evaluation"] = str(ev.path)
                row["bar_passed"] = sum(bool(v) for v in bar.values() if v is not None)
                row["bar_checked"] = sum(v is not None for v in bar.values())
                row["gc_diverged"] = int(sum(diverged.values()))
                row.update({f"bar/{k}": v for k, v in bar.items()})
            rows.append(row)
    cols = ["run", "d", "M", "seed", "run_id", "n_parameters", "final_train_loss",
            "final_val_loss", "best_val_loss", "mse_mean", *(f"mse/{k}" for k in plants),
            "closed_loop_diverged"]  # fmt: skip
    return pd.DataFrame(rows, columns=list(dict.fromkeys([*cols, *(k for r in rows for k in r)])))
