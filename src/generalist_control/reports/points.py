"""Every run behind the ablation's points, each seed apart (``points.csv`` of the report).

The figures draw one run per point; the DVC ablation trains a second seed of some points,
and the claims and the tables use every seed (:func:`seed_runs`, :func:`points_frame`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.common.jsonsafe import finite
from generalist_control.reports.evaluations import Evaluation, bar_of
from generalist_control.reports.runs import RunPoint, unique_points

__all__ = ["infer_recipe", "points_frame", "run_label", "seed_runs"]

Config = tuple[int, int]


def run_label(p: RunPoint) -> str:
    """``d32-M3-s42``: a run as the tables name it (its point and its seed)."""
    return f"d{p.hidden}-M{p.experts}" + (f"-s{p.seed}" if p.seed is not None else "")


def seed_runs(
    points: Sequence[RunPoint], sweeps: Mapping[str, Mapping[int, RunPoint | None]]
) -> dict[Config, list[RunPoint]]:
    """Per configuration (d, M) of the sweeps, its newest run of each seed, by seed.

    Parameters
    ----------
    points : sequence of RunPoint
        Every run found (:func:`~generalist_control.reports.runs.runs_from_mlflow`).
    sweeps : mapping
        The runs drawn (:func:`~generalist_control.reports.runs.select_sweeps`): they give
        the configurations, and a configuration drawn from a run that ``points`` lacks keeps
        that run.
    """
    out: dict[Config, list[RunPoint]] = {}
    for drawn in unique_points(sweeps):
        config = (drawn.hidden, drawn.experts)
        by_seed: dict[int | None, RunPoint] = {}
        for p in sorted(points, key=lambda p: -p.start_time):
            if (p.hidden, p.experts) == config:
                by_seed.setdefault(p.seed, p)
        by_seed.setdefault(drawn.seed, drawn)
        out[config] = sorted(by_seed.values(), key=lambda p: (p.seed is None, p.seed or 0))
    return out


def infer_recipe(runs: Sequence[RunPoint]) -> str:
    """The runs' recipe: ``paper`` if none scales windows or runs DAgger, else ``default``.

    Which of the paper's figures are comparable depends on it (:mod:`.claims`).
    """
    if runs and all(
        str(p.params.get("model.window_scale", "")).lower() == "false"
        and not any(k.startswith("dagger.") for k in p.params)
        for p in runs
    ):
        return "paper"
    return "default"


def points_frame(
    by_config: Mapping[Config, Sequence[RunPoint]],
    plants: Sequence[str],
    evaluations: Mapping[str, Evaluation],
) -> pd.DataFrame:
    """One row per run: its point, seed, parameters, losses, scores and verdicts.

    Columns ``run, d, M, seed, run_id, n_parameters, final_train_loss, final_val_loss,
    best_val_loss, mse_mean`` (over ``plants`` it has a score for), ``mse/<plant>``,
    ``closed_loop_diverged``, then from its evaluation (empty without one) ``evaluation``
    (its folder), ``bar_passed``, ``bar_checked``, ``gc_diverged`` (GC runs diverged, every
    scenario) and ``bar/<verdict>`` (True, False; empty: not measured).
    """
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
                bar = bar_of(ev.summary)
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
