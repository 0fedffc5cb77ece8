"""The ablation report (paper, Section 7) redrawn from the MLflow training runs.

Run ``python -m generalist_control.report`` (Hydra; settings in ``conf/report``) or
``dvc repro report``. Nothing is trained here: the report reads the finished training runs
of one MLflow experiment (kind ``sweep`` by default, optionally only the children of
``report.parent_run``; :mod:`generalist_control.reports.selection`), each of which carries
``model.hidden`` and ``experts`` (params), ``n_parameters``, the per-epoch ``train/loss``
history and ``closed_loop/mse/<plant>``, the GC-vs-LQI unit-step output MSE on the ablation
set. The two sweeps are

* the hidden dimension ``d`` in ``report.hidden`` at ``M = report.baseline.experts``
  (created by ``python train.py -m model.hidden=16,32,64``), and
* the expert count ``M`` in ``report.experts`` at ``d = report.baseline.hidden``
  (``python train.py -m experts=1,3,5``);

when several runs share a configuration the newest one is used. Runs that differ in more
than ``d`` and ``M`` (e.g. ``trainer.max_epochs``) are refused by name, or with
``report.allow_mixed=true`` reported under a loud warning. A configuration without a
run is drawn and tabulated as "no run"; an experiment without any finished training run is
an error (:class:`NoAblationRunsError`) that names the commands above.

Outputs under ``report.out_dir`` (``reports/ablation``), written to a temporary directory
and renamed into place, a PNG and a CSV for each figure:

* ``mse_hidden``, ``mse_experts``: per-plant closed-loop output MSE (grouped bars, log y);
* ``loss_hidden``, ``loss_experts``: training-loss curves (``train/loss`` per epoch);
* ``params_vs_mse``: parameter count against the mean MSE over the plants;
* ``gate_weights``: mean gate weight per expert and plant of the ``M = report.gate.experts``
  model (see :func:`~generalist_control.reports.gates.gate_weights`);
* ``fig_hidden_ablation.png``, ``fig_expert_ablation.png``: the paper's two-panel layouts;
* ``claims.csv``: the paper's Section 7 claim by claim, ours beside it and a verdict
  (:mod:`generalist_control.reports.claims`);
* ``points.csv``: every run behind the points, each seed apart, with its losses, scores and
  its evaluation's quality-bar verdicts (:mod:`generalist_control.reports.points`);
* ``scenarios.csv``: per run, scenario and plant, GC's score over LQI's, from the runs'
  evaluations (``report.evaluations_dir``, :mod:`generalist_control.reports.evaluations`);
* ``comparison.md`` (all of it in words and tables, :mod:`.comparison`), ``runs.csv`` (the
  run drawn for each point) and ``summary.json`` (the same figures, the claims, the recipe,
  the provenance, read by the results page).

The data come from :mod:`generalist_control.reports.runs` and
:mod:`generalist_control.reports.gates`, the drawing from
:mod:`generalist_control.reports.figures`, the paper comparison from
:mod:`generalist_control.reports.comparison`. Everything is logged to a ``report`` run of the
experiment of kind ``report`` (:mod:`generalist_control.reports.report_run`).
The drawing functions take a Matplotlib
``Axes`` and data frames, so notebooks reuse them (``notebooks/02_mlflow_comparison.ipynb``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from omegaconf import DictConfig

from generalist_control.common.atomic import (
    check_replaceable,
    publish_directory,
    staging_directory,
)
from generalist_control.common.configs import as_dict
from generalist_control.common.jsonsafe import finite, strict
from generalist_control.evaluation.provenance import provenance
from generalist_control.reports.claims import claims_records, verdict_counts
from generalist_control.reports.comparison import comparison_markdown
from generalist_control.reports.figures import (
    draw_gate_heatmap,
    draw_loss_curves,
    draw_mse_bars,
    draw_params_vs_mse,
    new_figure,
    placeholder,
)
from generalist_control.reports.gates import gate_weights, policy_of_run
from generalist_control.reports.report_run import log_report
from generalist_control.reports.runs import (
    NO_RUN,
    SWEEP_COMMANDS,
    SWEEPS,
    RunPoint,
    mlflow_client,
    point_label,
    unique_points,
)
from generalist_control.reports.selection import select_runs
from generalist_control.reports.tables import Inputs, inputs_from_config, report_tables
from generalist_control.tracking import mlflow_utils

__all__ = ["OWNED", "Inputs", "build_report", "runs_table", "write_report"]

log = logging.getLogger(__name__)


def runs_table(sweeps: Mapping[str, Mapping[int, RunPoint | None]]) -> pd.DataFrame:
    """One row per sweep point: its run (or "no run") and the run's figures."""
    rows = []
    for sweep, by_value in sweeps.items():
        for value, p in by_value.items():
            rows.append(
                {
                    "sweep": sweep,
                    "value": value,
                    "label": point_label(sweep, value),
                    "status": "ok" if p else NO_RUN,
                    "run_id": p.run_id if p else None,
                    "run_name": p.run_name if p else None,
                    "hidden": p.hidden if p else None,
                    "experts": p.experts if p else None,
                    "seed": p.seed if p else None,
                    "n_parameters": p.n_parameters if p else None,
                    "final_train_loss": p.train_loss if p else None,
                    "final_val_loss": p.val_loss if p else None,
                    "closed_loop_diverged": p.diverged if p else None,
                }
            )
    return pd.DataFrame(rows)


_EXT = ("csv", "png")

#: The exact names a report writes: a folder without the outputs marker that holds only
#: these (one written before markers, :mod:`generalist_control.common.atomic`) may be replaced.
OWNED: dict[str, str | None] = dict.fromkeys(
    [
        *(f"{kind}_{sweep}.{ext}" for kind in ("mse", "loss") for sweep in SWEEPS for ext in _EXT),
        "params_vs_mse.csv",
        "params_vs_mse.png",
        "gate_weights.csv",
        "gate_weights.png",
        "fig_hidden_ablation.png",
        "fig_expert_ablation.png",
        "runs.csv",
        "points.csv",
        "claims.csv",
        "scenarios.csv",
        "comparison.md",
        "summary.json",
    ]
)


def _gate_model(
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    gate: Mapping[str, Any],
    base: Mapping[str, int],
    client: Any,
) -> tuple[RunPoint | None, pd.DataFrame | None]:
    """The run of the gate-weight model (``M = gate.experts`` at the baseline d) and its gates."""
    gate_m = int(gate.get("experts", 5))
    gate_run = sweeps.get("experts", {}).get(gate_m)
    if gate_run is None:
        same = (
            p for p in unique_points(sweeps) if (p.hidden, p.experts) == (base["hidden"], gate_m)
        )
        gate_run = next(same, None)
    if gate_run is None:
        return None, None
    policy, meta = policy_of_run(gate_run.run_id, client)
    gates = gate_weights(policy, meta, gate.get("plants"), float(gate.get("duration", 15.0)))
    return gate_run, gates


def _sweep_figures(
    staging: Path,
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    frames: Mapping[str, Any],
    base: Mapping[str, int],
) -> None:
    """Per sweep: MSE bars and loss curves; parameters against MSE; the paper's layouts."""
    mse, loss, params = frames["mse"], frames["loss"], frames["params"]
    for sweep in SWEEPS:
        mse[mse["sweep"] == sweep].to_csv(staging / f"mse_{sweep}.csv", index=False)
        loss[loss["sweep"] == sweep].to_csv(staging / f"loss_{sweep}.csv", index=False)
        fig, (ax,) = new_figure(7, 4)
        draw_mse_bars(ax, mse, sweep)
        fig.savefig(staging / f"mse_{sweep}.png", dpi=120)
        fig, (ax,) = new_figure(6, 4)
        draw_loss_curves(ax, loss, sweep, list(sweeps.get(sweep, {})), baseline=base)
        fig.savefig(staging / f"loss_{sweep}.png", dpi=120)
    params.to_csv(staging / "params_vs_mse.csv", index=False)
    fig, (ax,) = new_figure(6, 4)
    draw_params_vs_mse(ax, params)
    fig.savefig(staging / "params_vs_mse.png", dpi=120)
    fig, axes = new_figure(13, 4, ncols=2)  # the paper's Fig. hidden_ablation
    draw_mse_bars(axes[0], mse, "hidden")
    draw_loss_curves(axes[1], loss, "hidden", list(sweeps.get("hidden", {})), baseline=base)
    fig.savefig(staging / "fig_hidden_ablation.png", dpi=120)
    fig, axes = new_figure(13, 4, ncols=2)  # the paper's Fig. expert_ablation
    draw_mse_bars(axes[0], mse, "experts")
    expert_ids = {p.run_id for p in sweeps.get("experts", {}).values() if p}
    draw_params_vs_mse(axes[1], params[params["run_id"].isin(expert_ids)])
    fig.savefig(staging / "fig_expert_ablation.png", dpi=120)


def _gate_figure(
    staging: Path,
    gates: pd.DataFrame | None,
    gate_run: RunPoint | None,
    gate_m: int,
    base: Mapping[str, int],
) -> None:
    """The gate-weight heatmap and CSV (a placeholder without the model)."""
    gate_csv = staging / "gate_weights.csv"
    fig, (ax,) = new_figure(6, max(2.5, 0.8 + 0.3 * (len(gates) if gates is not None else 0)))
    if gates is not None and gate_run is not None:
        gates.to_csv(gate_csv)
        draw_gate_heatmap(ax, gates)
        ax.set_title(f"Mean gate weight, {gate_run.label} (run {gate_run.run_id[:8]})")
    else:
        cols = ["plant", *[f"expert_{i + 1}" for i in range(gate_m)]]
        pd.DataFrame(columns=cols).to_csv(gate_csv, index=False)
        placeholder(ax, f"{NO_RUN}: no finished run with d={base['hidden']}, M={gate_m}")
    fig.savefig(staging / "gate_weights.png", dpi=120)


def _summary(
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    gate_run: RunPoint | None,
    plants: Sequence[str],
    tables: Mapping[str, Any],
) -> dict[str, Any]:
    """``summary.json``: the runs of the points, the claims, the recipe, the provenance.

    Also the missing points, the gate model, per-config figures, the claims' verdict counts
    and the separating scenarios.
    """
    params, claims = tables["params"], tables["claims"]
    return {
        "points": {
            sweep: {point_label(sweep, v): (p.run_id if p else None) for v, p in by_v.items()}
            for sweep, by_v in sweeps.items()
        },
        "missing": [
            point_label(sweep, v)
            for sweep, by_v in sweeps.items()
            for v, p in by_v.items()
            if p is None
        ],
        "gate_run": gate_run.run_id if gate_run else None,
        "plants": list(plants),
        "configs": {
            row.label: {
                "run_id": row.run_id,
                "final_train_loss": finite(row.final_train_loss),
                "n_parameters": finite(row.n_parameters),
                "mse_mean": finite(row.mse_mean),
            }
            for row in params.itertuples()
        },
        "recipe": tables["recipe"],
        "claims": claims_records(claims),
        "claims_verdicts": verdict_counts(claims),
        "separating_scenarios": dict(tables["separating"]),
        "runs": {r: str(i) for i, r in tables["labels"].items()},
        "provenance": provenance(),
    }


def write_report(
    out_dir: str | Path,
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    plants: Sequence[str],
    client: Any | None = None,
    gate: Mapping[str, Any] | None = None,
    baseline: Mapping[str, int] | None = None,
    inputs: Inputs | None = None,
) -> dict[str, Any]:
    """Draw every figure and table from the selected runs; write them atomically.

    Parameters
    ----------
    out_dir : path
        Replaced as a whole (staged in a temporary sibling directory, then swapped in), and
        only if it holds nothing but a report's own outputs.
    sweeps : mapping
        From :func:`~generalist_control.reports.runs.select_sweeps`.
    plants : sequence of str
        Plants of the MSE figures (``closed_loop/mse/<plant>``).
    client : mlflow.tracking.MlflowClient, optional
    gate : mapping, optional
        ``experts`` (M of the gate-weight model, default 5), ``plants`` (None: all it
        knows), ``duration`` (s).
    baseline : mapping, optional
        ``hidden`` of the gate-weight model (default 32).
    inputs : Inputs, optional
        Every seed's runs, their evaluations, the recipe, the tolerances.

    Returns
    -------
    dict
        The summary also written to ``summary.json`` (:func:`_summary`).
    """
    check_replaceable(out_dir, OWNED, "report.out_dir")
    client = client or mlflow_client()
    inputs = inputs or Inputs()
    gate = dict(gate or {})
    base = {"hidden": 32, "experts": 3, **(baseline or {})}
    sweeps = {k: dict(v) for k, v in sweeps.items()}
    gate_run, gates = _gate_model(sweeps, gate, base, client)
    tables = report_tables(sweeps, plants, client, gates, inputs)
    with staging_directory(out_dir) as staging:
        _sweep_figures(staging, sweeps, tables, base)
        _gate_figure(staging, gates, gate_run, int(gate.get("experts", 5)), base)
        runs_table(sweeps).to_csv(staging / "runs.csv", index=False)
        for name in ("points", "claims", "scenarios"):
            tables[name].to_csv(staging / f"{name}.csv", index=False)
        text = comparison_markdown(
            tables, gates, gate_run, inputs.eval_summary, recipe=tables["recipe"]
        )
        (staging / "comparison.md").write_text(text)
        summary = _summary(sweeps, gate_run, plants, tables)
        (staging / "summary.json").write_text(json.dumps(strict(summary), indent=2) + "\n")
        publish_directory(staging, out_dir, OWNED, "report.out_dir")
    return summary


def build_report(cfg: DictConfig) -> dict[str, Any]:
    """Find the sweep runs, write ``report.out_dir`` and log the report to MLflow.

    Training runs that lie on neither sweep (e.g. a ``dvc exp run -S experts=4``) leave
    every point "no run" in the report, with a warning naming the sweep commands.

    Raises
    ------
    NoAblationRunsError
        If the experiment holds no finished training run at all; nothing is written.
    MixedRunsError
        If the runs differ in more than the swept keys and ``report.allow_mixed`` is false
        (:func:`~generalist_control.reports.selection.check_comparable`); nothing is written.
    """
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    rcfg = cfg.report
    client = mlflow_client(mlflow_utils.set_tracking(cfg.logger))
    experiment, sweeps, mixed, by_config = select_runs(cfg, client)
    baseline = as_dict(rcfg.baseline)
    plants = rcfg.get("plants")
    if plants is None:
        plants = (cfg.get("closed_loop") or {}).get("systems")
    plants = list(plants or [])
    if not plants:
        plants = sorted({k for p in unique_points(sweeps) for k in p.mse})
    out_dir = Path(rcfg.out_dir)
    gate = as_dict(rcfg.gate) if rcfg.get("gate") else {}
    inputs = inputs_from_config(cfg, by_config)
    summary = write_report(out_dir, sweeps, plants, client, gate, baseline, inputs)
    if summary["missing"]:
        log.warning(
            "no run for %s; create them with: %s",
            ", ".join(summary["missing"]),
            " and ".join(SWEEP_COMMANDS),
        )
    if mixed:
        summary["mixed"] = mixed
    if rcfg.get("log_mlflow", True):
        summary["report_run_id"] = log_report(cfg, experiment, out_dir, summary)
    log.info("ablation report written to %s", out_dir)
    return summary
