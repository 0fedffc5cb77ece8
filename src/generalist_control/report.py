"""The ablation report (paper, Section 7) redrawn from the MLflow training runs.

Run ``python -m generalist_control.report`` (Hydra; settings in ``conf/report``) or
``dvc repro report``. Nothing is trained here: the report reads the finished training runs
of one MLflow experiment, each of which carries ``model.hidden`` and ``experts`` (params),
``n_parameters``, the per-epoch ``train/loss`` history and ``closed_loop/mse/<plant>``, the
GC-vs-LQI unit-step output MSE on the ablation set. The two sweeps are

* the hidden dimension ``d`` in ``report.hidden`` at ``M = report.baseline.experts``
  (created by ``python train.py -m model.hidden=16,32,64``), and
* the expert count ``M`` in ``report.experts`` at ``d = report.baseline.hidden``
  (``python train.py -m experts=1,3,5``);

when several runs share a configuration the newest one is used. A configuration without a
run is drawn and tabulated as "no run"; an experiment without any finished training run is
an error (:class:`NoAblationRunsError`) that names the commands above.

Outputs under ``report.out_dir`` (``reports/ablation``), written to a temporary directory
and renamed into place, a PNG and a CSV for each figure:

* ``mse_hidden``, ``mse_experts``: per-plant closed-loop output MSE (grouped bars, log y);
* ``loss_hidden``, ``loss_experts``: training-loss curves (``train/loss`` per epoch);
* ``params_vs_mse``: parameter count against the mean MSE over the plants;
* ``gate_weights``: mean gate weight per expert and plant of the ``M = report.gate.experts``
  model (see :func:`gate_weights` for how the weights are gathered);
* ``fig_hidden_ablation.png``, ``fig_expert_ablation.png``: the paper's two-panel layouts;
* ``comparison.md`` (our figures beside the paper's, :data:`generalist_control.paper.ABLATION`),
  ``runs.csv`` (the runs used) and ``summary.json``.

The data come from :mod:`generalist_control.ablation_runs`, the drawing from
:mod:`generalist_control.ablation_figures` (both re-exported here). Everything is logged to a
``report`` run of the same experiment (tag ``gc.run_type =
report``), which the run search leaves out. The drawing functions take a Matplotlib
``Axes`` and data frames, so notebooks reuse them (``notebooks/02_mlflow_comparison.ipynb``).
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from generalist_control.ablation_figures import (
    draw_gate_heatmap,
    draw_loss_curves,
    draw_mse_bars,
    draw_params_vs_mse,
    fmt_value,
    new_figure,
    placeholder,
)
from generalist_control.ablation_runs import (
    NO_RUN,
    NOT_AVAILABLE,
    RUN_TYPE_TAG,
    SWEEP_COMMANDS,
    SWEEPS,
    NoAblationRunsError,
    RunPoint,
    gate_weights,
    loss_frame,
    mlflow_client,
    mse_frame,
    params_frame,
    point_label,
    policy_of_run,
    runs_from_mlflow,
    select_sweeps,
    unique_points,
)
from generalist_control.paper import ABLATION
from generalist_control.paths import HYDRA_CONFIG_PATH

log = logging.getLogger(__name__)

__all__ = [
    "RUN_TYPE_TAG",
    "SWEEP_COMMANDS",
    "NoAblationRunsError",
    "RunPoint",
    "comparison_markdown",
    "draw_gate_heatmap",
    "draw_loss_curves",
    "draw_mse_bars",
    "draw_params_vs_mse",
    "gate_weights",
    "loss_frame",
    "mse_frame",
    "params_frame",
    "policy_of_run",
    "run",
    "runs_from_mlflow",
    "runs_table",
    "select_sweeps",
    "write_report",
]

# --- the comparison with the paper --------------------------------------------------------


def _parse_key(key: str) -> tuple[int, int]:
    m = re.fullmatch(r"d=(\d+),M=(\d+)", key)
    if not m:
        raise ValueError(f"unexpected configuration key '{key}'")
    return int(m.group(1)), int(m.group(2))


def comparison_markdown(
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    mse: pd.DataFrame,
    gates: pd.DataFrame | None,
    gate_run: RunPoint | None,
    eval_summary: Mapping[str, Any] | None = None,
) -> str:
    """Markdown: our ablation figures beside the paper's, and the per-plant MSE tables."""
    by_cfg = {(p.hidden, p.experts): p for p in unique_points(sweeps)}

    def find(key: str) -> RunPoint | None:
        return by_cfg.get(_parse_key(key))

    def mse_of(p: RunPoint | None, plant: str) -> str:
        if p is None:
            return NO_RUN
        return fmt_value(p.mse.get(plant))

    def run_of(p: RunPoint | None) -> str:
        return f"`{p.run_id[:8]}`" if p else ""

    lines = [
        "# Ablation study (Section 7): our runs beside the paper",
        "",
        "Redrawn from the MLflow training runs by `python -m generalist_control.report`. "
        '"no run": no finished run of that configuration; "no score": the run has no score '
        "(diverged, or not trained on the plant). Our training loss is the MSE on normalised "
        "controls (see docs/training.md); MSE is GC against LQI, unit step, ablation set.",
        "",
        "| quantity | configuration | paper | ours | run |",
        "| --- | --- | --- | --- | --- |",
    ]
    for key, ref in ABLATION["final_train_loss"].items():
        p = find(key)
        ours = NO_RUN if p is None else fmt_value(p.train_loss)
        lines.append(f"| final training loss | {key} | {fmt_value(ref)} | {ours} | {run_of(p)} |")
    for key, ref in ABLATION["parameters"].items():
        p = find(key)
        ours = (
            NO_RUN if p is None else (f"{p.n_parameters:,}" if p.n_parameters else NOT_AVAILABLE)
        )
        approx = "" if key == "d=32,M=3" else "≈"
        lines.append(f"| parameters | {key} | {approx}{ref:,} | {ours} | {run_of(p)} |")
    for name, plant in (("crazyflie_mse", "crazyflie_altitude"), ("hvac_mse", "hvac_two_zone")):
        for key, ref in ABLATION[name].items():
            p = find(key)
            lines.append(
                f"| {plant} MSE | {key} | {fmt_value(ref)} | {mse_of(p, plant)} | {run_of(p)} |"
            )
    gate_cfg = gate_run.label if gate_run else "d=32,M=5"  # the paper's gate model
    for plant, ref in ABLATION["gate_weights_m5"].items():
        ((expert, weight),) = ref.items()
        paper = f"{expert.replace('_', ' ')}: {weight:.0%}"
        if gates is None or gate_run is None:
            ours = NO_RUN
        elif plant not in gates.index:
            ours = "not trained on it"
        else:
            row = gates.loc[plant]
            ours = f"{row.idxmax().replace('_', ' ')}: {row.max():.0%} (dominant)"
        lines.append(
            f"| gate weight, {plant} | {gate_cfg} | {paper} | {ours} | {run_of(gate_run)} |"
        )
    lines += [
        "",
        "Expert numbering is arbitrary (any permutation of the experts is the same model), so "
        "for the gate weights compare the dominant expert's share, not its index.",
    ]
    for sweep, symbol in SWEEPS.items():
        part = mse[mse["sweep"] == sweep]
        if part.empty:
            continue
        values = list(dict.fromkeys(part["value"]))
        lines += [
            "",
            f"## Output MSE by {symbol} (figure `mse_{sweep}.png`)",
            "",
            "| plant | " + " | ".join(point_label(sweep, v) for v in values) + " |",
            "| --- |" + " --- |" * len(values),
        ]
        for plant, rows in part.groupby("plant", sort=False):
            cells = []
            for v in values:
                r = rows[rows["value"] == v].iloc[0]
                cells.append(fmt_value(r["mse"]) if r["status"] == "ok" else r["status"])
            lines.append(f"| {plant} | " + " | ".join(cells) + " |")
    if eval_summary:
        qb = eval_summary.get("quality_bar", {})
        lines += [
            "",
            "## The pipeline's model (evaluate stage, reports/eval/summary.json)",
            "",
            "| quality bar | met |",
            "| --- | --- |",
            *[f"| {k} | {v} |" for k, v in qb.items()],
        ]
    return "\n".join(lines) + "\n"


# --- the report ---------------------------------------------------------------------------


def _publish(staging: Path, out_dir: Path) -> None:
    old = out_dir.with_name(f".{out_dir.name}.old-{os.getpid()}")
    if out_dir.exists():
        os.replace(out_dir, old)
    os.replace(staging, out_dir)
    shutil.rmtree(old, ignore_errors=True)


def _finite(value: Any) -> float | None:
    """A finite float, or None (for JSON)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


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
                    "n_parameters": p.n_parameters if p else None,
                    "final_train_loss": p.train_loss if p else None,
                    "closed_loop_diverged": p.diverged if p else None,
                }
            )
    return pd.DataFrame(rows)


def write_report(
    out_dir: str | Path,
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    plants: Sequence[str],
    client: Any | None = None,
    gate: Mapping[str, Any] | None = None,
    baseline: Mapping[str, int] | None = None,
    eval_summary: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Draw every figure and table from the selected runs; write them atomically.

    Parameters
    ----------
    out_dir : path
        Replaced as a whole (staged in a temporary sibling directory, then renamed).
    sweeps : mapping
        From :func:`select_sweeps`.
    plants : sequence of str
        Plants of the MSE figures (``closed_loop/mse/<plant>``).
    client : mlflow.tracking.MlflowClient, optional
    gate : mapping, optional
        ``experts`` (M of the gate-weight model, default 5), ``plants`` (None: all it
        knows), ``duration`` (s).
    baseline : mapping, optional
        ``hidden`` of the gate-weight model (default 32).
    eval_summary : mapping, optional
        The evaluate stage's ``summary.json``, quoted in ``comparison.md``.

    Returns
    -------
    dict
        The summary also written to ``summary.json``: run ids per point, missing points,
        the gate model's run.
    """
    client = client or mlflow_client()
    gate = dict(gate or {})
    base = {"hidden": 32, "experts": 3, **(baseline or {})}
    gate_m = int(gate.get("experts", 5))
    sweeps = {k: dict(v) for k, v in sweeps.items()}
    mse = mse_frame(sweeps, plants)
    loss = loss_frame(sweeps, client)
    params = params_frame(sweeps, plants)
    gate_run = sweeps.get("experts", {}).get(gate_m)
    if gate_run is None:
        gate_run = next(
            (
                p
                for p in unique_points(sweeps)
                if (p.hidden, p.experts) == (base["hidden"], gate_m)
            ),
            None,
        )
    gates = None
    if gate_run is not None:
        policy, meta = policy_of_run(gate_run.run_id, client)
        gates = gate_weights(policy, meta, gate.get("plants"), float(gate.get("duration", 15.0)))

    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
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

        gate_csv = staging / "gate_weights.csv"
        fig, (ax,) = new_figure(6, max(2.5, 0.8 + 0.3 * (len(gates) if gates is not None else 0)))
        if gates is not None:
            gates.to_csv(gate_csv)
            draw_gate_heatmap(ax, gates)
            ax.set_title(f"Mean gate weight, {gate_run.label} (run {gate_run.run_id[:8]})")
        else:
            cols = ["plant", *[f"expert_{i + 1}" for i in range(gate_m)]]
            pd.DataFrame(columns=cols).to_csv(gate_csv, index=False)
            placeholder(ax, f"{NO_RUN}: no finished run with d={base['hidden']}, M={gate_m}")
        fig.savefig(staging / "gate_weights.png", dpi=120)

        fig, axes = new_figure(13, 4, ncols=2)  # the paper's Fig. hidden_ablation
        draw_mse_bars(axes[0], mse, "hidden")
        draw_loss_curves(axes[1], loss, "hidden", list(sweeps.get("hidden", {})), baseline=base)
        fig.savefig(staging / "fig_hidden_ablation.png", dpi=120)
        fig, axes = new_figure(13, 4, ncols=2)  # the paper's Fig. expert_ablation
        draw_mse_bars(axes[0], mse, "experts")
        expert_ids = {p.run_id for p in sweeps.get("experts", {}).values() if p}
        draw_params_vs_mse(axes[1], params[params["run_id"].isin(expert_ids)])
        fig.savefig(staging / "fig_expert_ablation.png", dpi=120)

        runs_table(sweeps).to_csv(staging / "runs.csv", index=False)
        text = comparison_markdown(sweeps, mse, gates, gate_run, eval_summary)
        (staging / "comparison.md").write_text(text)
        summary = {
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
                    "final_train_loss": _finite(row.final_train_loss),
                    "n_parameters": _finite(row.n_parameters),
                    "mse_mean": _finite(row.mse_mean),
                }
                for row in params.itertuples()
            },
        }
        (staging / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        os.chmod(staging, 0o755)
        _publish(staging, out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return summary


def _log_to_mlflow(
    cfg: DictConfig, experiment: str, out_dir: Path, summary: Mapping[str, Any]
) -> str:
    """Log the report as a ``report`` run of the experiment; return its run id."""
    import mlflow

    from generalist_control import mlflow_utils

    rcfg = cfg.report
    logger = {
        **OmegaConf.to_container(cfg.logger, resolve=True),
        "experiment_name": experiment,
        "run_name": rcfg.get("run_name") or "ablation-report",
    }
    with mlflow_utils.mlflow_run(logger) as active:
        mlflow.set_tags(
            {
                RUN_TYPE_TAG: "report",
                "report.kind": "ablation",
                "report.missing": ", ".join(summary["missing"]) or "none",
            }
        )
        flat = mlflow_utils.flatten_params({"report": OmegaConf.to_container(rcfg, resolve=True)})
        mlflow.log_params(flat)
        mlflow.log_dict(dict(summary), "ablation/summary.json")
        mlflow.log_artifacts(str(out_dir), "ablation")
        metrics = {"report/missing_points": float(len(summary["missing"]))}
        for label, fig in summary["configs"].items():
            key = label.replace("=", "").replace(",", "_")  # d32_M3
            for name in ("final_train_loss", "n_parameters", "mse_mean"):
                value = fig.get(name)
                if value is not None and np.isfinite(value):
                    metrics[f"ablation/{name}/{key}"] = float(value)
        mlflow.log_metrics(metrics)
        return active.info.run_id


def run(cfg: DictConfig) -> dict[str, Any]:
    """Find the sweep runs, write ``report.out_dir`` and log the report to MLflow.

    Training runs that lie on neither sweep (e.g. a ``dvc exp run -S experts=4``) leave
    every point "no run" in the report, with a warning naming the sweep commands.

    Raises
    ------
    NoAblationRunsError
        If the experiment holds no finished training run at all; nothing is written.
    """
    from generalist_control import mlflow_utils

    if cfg.get("threads"):
        import torch

        torch.set_num_threads(int(cfg.threads))
    rcfg = cfg.report
    experiment = rcfg.get("experiment_name") or cfg.logger.experiment_name
    uri = mlflow_utils.set_tracking(cfg.logger)
    client = mlflow_client(uri)
    points = runs_from_mlflow(experiment, rcfg.get("filter_string") or "", client)
    baseline = OmegaConf.to_container(rcfg.baseline, resolve=True)
    sweeps = select_sweeps(points, list(rcfg.hidden), list(rcfg.experts), baseline)
    if not points:
        raise NoAblationRunsError(
            f"no finished training run in MLflow experiment '{experiment}' at {uri} "
            f"(filter: {rcfg.get('filter_string')!r}). Create the ablation runs with:\n  "
            + "\n  ".join(SWEEP_COMMANDS)
        )
    plants = rcfg.get("plants")
    if plants is None:
        plants = (cfg.get("closed_loop") or {}).get("systems")
    plants = list(plants or [])
    if not plants:
        plants = sorted({k for p in unique_points(sweeps) for k in p.mse})
    eval_summary = None
    summary_path = Path(cfg.paths.get("reports_dir", "reports/eval")) / "summary.json"
    if summary_path.is_file():
        eval_summary = json.loads(summary_path.read_text())
    out_dir = Path(rcfg.out_dir)
    gate = OmegaConf.to_container(rcfg.gate, resolve=True) if rcfg.get("gate") else {}
    summary = write_report(out_dir, sweeps, plants, client, gate, baseline, eval_summary)
    if summary["missing"]:
        log.warning(
            "no run for %s; create them with: %s",
            ", ".join(summary["missing"]),
            " and ".join(SWEEP_COMMANDS),
        )
    if rcfg.get("log_mlflow", True):
        summary["report_run_id"] = _log_to_mlflow(cfg, experiment, out_dir, summary)
    log.info("ablation report written to %s", out_dir)
    return summary


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``report`` stage."""
    run(cfg)


if __name__ == "__main__":
    main()
