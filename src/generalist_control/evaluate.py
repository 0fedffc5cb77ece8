"""Closed-loop evaluation of a trained policy against LQI (``python -m ...evaluate``).

Every scenario of ``conf/evaluation`` runs three controllers on each plant it applies to:
the learned Generalist Controller (GC), the LQI expert, and LQI with anti-windup
(LQI-AW, conditional integration against the scenario's actuator limits). A policy that
integrates the tracking error (``model.integral``) winds up like LQI, so in scenarios with
actuator limits it also runs as GC-AW: the same policy, its runtime told the limits that
LQI-AW knows (:meth:`~generalist_control.runtime.PolicyRuntime.set_actuator_limits`).
All plants of a scenario are simulated in lockstep so the policy is called once per sample
for all of them. A run that diverges is reported as diverged (metric ``diverged`` = 1,
other metrics NaN), never as a huge number in an average.

Outputs under ``paths.reports_dir`` (default ``reports/eval``): ``metrics.csv`` in long form
(system, scenario, controller, run, metric, value), ``summary.json`` (the quality-bar
figures, DVC metrics), ``table2.md`` (the paper's Table 2 layout with the paper's values
beside ours), ``table_all.md`` (the same for every plant), ``responses.csv`` (DVC plots)
and PNG plots; all are logged to the MLflow run of the evaluated model.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from generalist_control import mlflow_utils
from generalist_control.catalog import plants_from_config
from generalist_control.crazyflie import fly
from generalist_control.lqi import AntiWindupLQIController, LQIController
from generalist_control.metrics import step_metrics, tracking_metrics
from generalist_control.paths import HYDRA_CONFIG_PATH
from generalist_control.plants import MAX_ORDER, Plant
from generalist_control.runtime import PolicyController, PolicyRuntime
from generalist_control.scenarios import perturbation, references
from generalist_control.simulate import (
    BatchController,
    PerPlantController,
    Perturbation,
    Run,
    Trajectory,
    simulate_many,
)

__all__ = [
    "CONTROLLERS",
    "ClosedLoopValidation",
    "closed_loop_score",
    "evaluate",
    "output_mse",
    "run",
    "summarise",
]

log = logging.getLogger(__name__)

CONTROLLERS = ("GC", "LQI", "LQI-AW")
#: Run as well where a scenario limits the actuator and the policy integrates.
GC_ANTI_WINDUP = "GC-AW"
STEP_KINDS = ("step", "random_steps")


class SinglePlantPolicy:
    """The runtime as a single-plant controller (for the Crazyflie loop)."""

    def __init__(self, runtime: PolicyRuntime, plant: str) -> None:
        self.runtime, self.plant = runtime, plant

    def reset(self, batch_size: int) -> None:
        """One runtime row per run."""
        self.runtime.reset([self.plant] * batch_size)

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls for unpadded states."""
        padded = np.zeros((x.shape[0], MAX_ORDER))
        padded[:, : x.shape[1]] = x
        return self.runtime.step(padded, r)  # an integrating policy: y = C x (its meta)


def _controller(name: str, runtime: PolicyRuntime, pert: Perturbation | None) -> BatchController:
    if name == "GC":
        return PolicyController(runtime)
    if name == GC_ANTI_WINDUP:
        return PolicyController(runtime, pert)
    if name == "LQI":
        return PerPlantController(LQIController)
    limits = pert or Perturbation()
    return PerPlantController(lambda p: AntiWindupLQIController(p, limits))


def _rows(
    system: str, scenario: str, controller: str, kind: str, tr: Trajectory
) -> list[tuple[str, str, str, int, str, float]]:
    if kind in STEP_KINDS:
        m = step_metrics(tr.t[:-1], tr.y[:, :-1], tr.u, tr.r)
    else:
        m = tracking_metrics(tr.t[:-1], tr.y[:, :-1], tr.r)
    out = []
    for i in range(tr.r.shape[0]):
        bad = bool(tr.diverged[i])
        out.append((system, scenario, controller, i, "diverged", float(bad)))
        for key, values in m.items():
            out.append((system, scenario, controller, i, key, np.nan if bad else float(values[i])))
    return out


def evaluate(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    scenarios: Mapping[str, Mapping[str, Any]],
    crazyflie: Mapping[str, Any] | None = None,
) -> tuple[pd.DataFrame, dict[str, dict[str, dict[str, Trajectory]]]]:
    """Run every scenario for every controller; return long-form metrics and trajectories.

    Returns
    -------
    metrics : DataFrame
        Columns ``system, scenario, controller, run, metric, value``.
    trajectories : dict
        ``trajectories[scenario][controller][system]``.
    """
    missing = [p.name for p in plants if p.name not in runtime.tags]
    if missing:
        raise KeyError(
            f"the policy was not trained on {', '.join(missing)}; it knows "
            f"{', '.join(runtime.systems)}. Evaluate a set it was trained on (systems=...)"
        )
    rows: list[tuple] = []
    trajs: dict[str, dict[str, dict[str, Trajectory]]] = {}
    for name, spec in scenarios.items():
        only = spec.get("plants")
        chosen = [p for p in plants if only is None or p.name in only]
        if not chosen:
            continue
        pert = perturbation(name, spec)
        runs = []
        for p in chosen:
            r, x0 = references(name, spec, p)
            runs.append(Run(p, r, x0, pert))
        trajs[name] = {}
        limited = pert is not None and (pert.u_limit is not None or pert.rate_limit is not None)
        extra = (GC_ANTI_WINDUP,) if limited and runtime.integral else ()
        for ctrl in (*CONTROLLERS, *extra):
            results = simulate_many(runs, _controller(ctrl, runtime, pert))
            trajs[name][ctrl] = {p.name: tr for p, tr in zip(chosen, results, strict=True)}
            for p, tr in zip(chosen, results, strict=True):
                rows += _rows(p.name, name, ctrl, spec["kind"], tr)
    if crazyflie and any(p.name == "crazyflie_altitude" for p in plants):
        plant = next(p for p in plants if p.name == "crazyflie_altitude")
        steps = int(round(float(crazyflie.get("duration", 15.0)) * 100))
        r = np.full((int(crazyflie.get("runs", 4)), steps), float(crazyflie.get("amplitude", 1.0)))
        ctrls = {
            "GC": SinglePlantPolicy(runtime, plant.name),
            "LQI": LQIController(plant),
            "LQI-AW": LQIController(plant),  # no known limits to wind up against here
        }
        trajs["crazyflie_sim2real"] = {}
        for ctrl, c in ctrls.items():
            tr = fly(c, r, control_dt=plant.dt, seed=int(crazyflie.get("seed", 0)))
            trajs["crazyflie_sim2real"][ctrl] = {plant.name: tr}
            rows += _rows(plant.name, "crazyflie_sim2real", ctrl, "step", tr)
    df = pd.DataFrame(rows, columns=["system", "scenario", "controller", "run", "metric", "value"])
    return df, trajs


def output_mse(
    runtime: PolicyRuntime, plants: Sequence[Plant], duration: float = 15.0
) -> dict[str, float]:
    """The ablation study's closed-loop score: per plant, the output MSE of GC against LQI.

    Both controllers track a unit step (scaled by the plant's ``amplitude_scale``) from
    rest for ``duration`` seconds; the score is the mean of ``(y_GC - y_LQI)**2`` over the
    samples. A diverged GC run scores ``inf``.
    """
    spec = {"kind": "step", "amplitude": 1.0, "duration": float(duration)}
    runs = [Run(p, *references("step", spec, p), None) for p in plants]
    gc = simulate_many(runs, PolicyController(runtime))
    lqi = simulate_many(runs, PerPlantController(LQIController))
    return {
        p.name: float("inf") if a.diverged.any() else float(np.mean((a.y - b.y) ** 2))
        for p, a, b in zip(plants, gc, lqi, strict=True)
    }


def _worst(values: pd.Series, key: str, system_key: str | None = None) -> dict[str, Any]:
    """Largest value and its system; with nothing finite (all diverged): inf and None."""
    system_key = system_key or f"worst_{key.split('_')[0]}_system"
    if values.empty:
        return {f"worst_{key}": float("inf"), system_key: None}
    return {f"worst_{key}": float(values.max()), system_key: str(values.idxmax())}


def closed_loop_score(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    amplitudes: Sequence[float] = (1.0, -3.0),
    duration: float = 10.0,
) -> dict[str, float]:
    """Per plant, GC-vs-LQI output error on steps, relative to the LQI response, capped at 1.

    ``mean((y_GC - y_LQI)**2) / mean(y_LQI**2)`` over steps of each amplitude (times the
    plant's ``amplitude_scale``) from rest; 1 for a diverged run (and at most 1 anyway), so
    the mean over plants is a bounded closed-loop validation score.
    """
    steps = int(round(duration / plants[0].dt))
    amps = np.asarray(amplitudes, dtype=float)
    runs = [Run(p, np.repeat(amps[:, None] * p.amplitude_scale, steps, axis=1)) for p in plants]
    gc = simulate_many(runs, PolicyController(runtime))
    lqi = simulate_many(runs, PerPlantController(LQIController))
    out = {}
    for p, a, b in zip(plants, gc, lqi, strict=True):
        if a.diverged.any():
            out[p.name] = 1.0
            continue
        err = np.mean((a.y - b.y) ** 2, axis=1) / np.maximum(np.mean(b.y**2, axis=1), 1e-300)
        out[p.name] = float(min(1.0, err.mean()))
    return out


class ClosedLoopValidation(L.Callback):
    """Log ``val/closed_loop`` after each validation: the mean :func:`closed_loop_score`.

    Open-loop validation MSE says little about the closed loop (a small error in the
    feedback of an unstable plant diverges), so with DAgger the best checkpoint is chosen
    on this score (``monitor: val/closed_loop``). Per plant: ``val/closed_loop/<plant>``.
    """

    def __init__(
        self,
        plants: Sequence[Plant],
        amplitudes: Sequence[float] = (1.0, -3.0),
        duration: float = 10.0,
    ) -> None:
        self.plants, self.amplitudes, self.duration = list(plants), amplitudes, duration

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Score the current policy in closed loop and log it."""
        if trainer.sanity_checking or not self.plants:
            return
        policy = pl_module.policy
        was_training = policy.training
        runtime = PolicyRuntime(policy, trainer.datamodule.meta())
        with torch.inference_mode():
            scores = closed_loop_score(runtime, self.plants, self.amplitudes, self.duration)
        policy.train(was_training)
        pl_module.log("val/closed_loop", float(np.mean(list(scores.values()))), logger=False)
        for name, v in scores.items():
            pl_module.log(f"val/closed_loop/{name}", v, logger=False)


def summarise(df: pd.DataFrame) -> dict[str, Any]:
    """Quality-bar figures: divergences, worst ISE/ITAE ratios GC/LQI, worst relative e_ss."""
    mean = df.groupby(["scenario", "controller", "system", "metric"])["value"].mean()
    out: dict[str, Any] = {"diverged": {}, "ratios": {}}
    for ctrl in [*CONTROLLERS, *sorted(set(df.controller) - set(CONTROLLERS))]:
        d = df[(df.controller == ctrl) & (df.metric == "diverged")]
        out["diverged"][ctrl] = {
            s: int(v) for s, v in d.groupby("scenario")["value"].sum().items() if v > 0
        }
    for scen in ("step", "random_steps"):
        if scen not in mean.index.get_level_values(0):
            continue
        gc, lqi = mean[scen]["GC"], mean[scen]["LQI"]
        ratio = {
            k: (gc.xs(k, level="metric") / lqi.xs(k, level="metric")).dropna()
            for k in ("ISE", "ITAE")
        }
        ess = gc.xs("relative_steady_state_error", level="metric").dropna()
        out["ratios"][scen] = {
            **_worst(ratio["ISE"], "ISE_ratio"),
            **_worst(ratio["ITAE"], "ITAE_ratio"),
            **_worst(ess, "relative_ess_GC", "worst_relative_ess_system"),
            "n_systems": int(len(ratio["ISE"])),
        }
    step = out["ratios"].get("step", {})
    out["quality_bar"] = {
        "stable_everywhere": not any(out["diverged"]["GC"].get(s) for s in STEP_KINDS),
        "ess_within_1pct": all(
            out["ratios"].get(s, {}).get("worst_relative_ess_GC", np.inf) <= 0.01
            for s in STEP_KINDS
        ),
        "ISE_ratio_le_1.15": step.get("worst_ISE_ratio", np.inf) <= 1.15,
        "ITAE_ratio_le_2.0": step.get("worst_ITAE_ratio", np.inf) <= 2.0,
    }
    return out


def _json_safe(obj: Any) -> Any:
    """Strict JSON (for ``dvc metrics``): non-finite floats become null."""
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _publish(staging: Path, out_dir: Path) -> None:
    old = out_dir.with_name(f".{out_dir.name}.old-{os.getpid()}")
    if out_dir.exists():
        os.replace(out_dir, old)
    os.replace(staging, out_dir)
    shutil.rmtree(old, ignore_errors=True)


def write_reports(
    df: pd.DataFrame,
    trajs: Mapping[str, Mapping[str, Mapping[str, Trajectory]]],
    out_dir: str | Path,
    plots: bool = True,
) -> dict[str, Any]:
    """Write the CSV, tables, summary and plots atomically to ``out_dir``; return the summary."""
    from generalist_control import eval_report

    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        df.to_csv(staging / "metrics.csv", index=False)
        summary = summarise(df)
        (staging / "summary.json").write_text(json.dumps(_json_safe(summary), indent=2) + "\n")
        (staging / "table2.md").write_text(eval_report.table2_markdown(df))
        (staging / "table_all.md").write_text(eval_report.table_all_markdown(df))
        eval_report.responses_csv(trajs).to_csv(staging / "responses.csv", index=False)
        if plots:
            eval_report.plot_all(trajs, staging / "plots")
        os.chmod(staging, 0o755)
        _publish(staging, out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return summary


def run(cfg: DictConfig) -> dict[str, Any]:
    """Load the policy, evaluate it on ``cfg.systems`` and write (and log) the reports."""
    source = cfg.get("policy") or str(Path(cfg.paths.models_dir) / "policy.ckpt")
    mlflow_utils.set_tracking(cfg.logger)  # for runs:/ and models:/ policy URIs
    runtime = PolicyRuntime.load(source, backend=cfg.evaluation.get("backend", "torch"))
    plants = plants_from_config(cfg.systems)
    scen = OmegaConf.to_container(cfg.evaluation.scenarios, resolve=True)
    cf = OmegaConf.to_container(cfg.evaluation.get("crazyflie") or {}, resolve=True)
    df, trajs = evaluate(runtime, plants, scen, cf)
    out_dir = Path(cfg.paths.reports_dir)
    summary = write_reports(df, trajs, out_dir, plots=bool(cfg.evaluation.get("plots", True)))
    from generalist_control.eval_report import log_to_mlflow

    log_to_mlflow(cfg, runtime.meta, summary, out_dir)
    log.info("evaluation written to %s: %s", out_dir, json.dumps(summary["quality_bar"]))
    return summary


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``evaluate`` stage."""
    run(cfg)


if __name__ == "__main__":
    main()
