"""Closed-loop evaluation: LQI as the policy scores 1.0, divergence, the entry point end to end."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from generalist_control.common.paths import conf_dir
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.evaluation.result_tables import (
    recipes_markdown,
    table2_markdown,
    table_all_markdown,
)
from generalist_control.evaluation.runner import evaluate
from generalist_control.evaluation.summary import summarise
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation import comparison
from generalist_control.simulation.comparison import (
    ClosedLoopScore,
    output_mse,
)
from generalist_control.simulation.lqi import LQIController
from helpers import run_command, tiny_train_overrides, train

REPO = Path(__file__).resolve().parents[1]
PLANTS = ("cstr", "hydraulic_actuator")
SCENARIOS = {
    "step": {"kind": "step", "amplitude": 1.0, "duration": 15.0},
    "random_steps": {"kind": "random_steps", "count": 3, "limit": 20.0, "seed": 0, "duration": 15},
    "sine": {"kind": "sine", "amplitude": 1.0, "omega": 0.5, "y0": 0.5, "duration": 6.0},
}


class LQIRuntime:
    """Duck-typed runtime whose 'policy' is the LQI law itself (integrator per row)."""

    integral = False  # its integrators are its own: the simulator passes no output

    def set_actuator_limits(self, u_limit=None, rate_limit=None) -> None:
        """Knows no actuator (plain LQI)."""

    def __init__(self, names, gain: float = 1.0) -> None:
        self.plants = {n: load_plant(n) for n in names}
        self.tags = {n: p.tag for n, p in self.plants.items()}
        self.systems = sorted(self.tags)
        self.gain = gain

    def reset(self, system) -> None:
        names = [system] if isinstance(system, str) else list(system)
        self.groups = []
        for name in dict.fromkeys(names):
            rows = np.array([i for i, n in enumerate(names) if n == name])
            ctrl = LQIController(self.plants[name])
            ctrl.reset(len(rows))
            self.groups.append((ctrl, self.plants[name].order, rows))

    def select(self, rows) -> None:
        """Go on with only ``rows`` of the batch, in that order (as PolicyRuntime.select)."""
        rows = np.asarray(rows)
        groups = []
        for ctrl, n, idx in self.groups:
            mine = np.flatnonzero(np.isin(rows, idx))  # their new positions
            if mine.size:
                ctrl.z = ctrl.z[np.searchsorted(idx, rows[mine])]
                groups.append((ctrl, n, mine))
        self.groups = groups

    def step(self, x, r):
        x, r = np.atleast_2d(x), np.atleast_1d(r)
        u = np.empty(len(r))
        for ctrl, n, rows in self.groups:
            u[rows] = ctrl.step(x[rows, :n], r[rows])
        return self.gain * u


def test_a_policy_that_is_the_lqi_law_scores_exactly_one():
    plants = [load_plant(n) for n in PLANTS]
    df, trajs = evaluate(LQIRuntime(PLANTS), plants, SCENARIOS)
    assert set(df.columns) == {"system", "scenario", "controller", "run", "metric", "value"}
    assert set(df.controller) == {"GC", "LQI", "LQI-AW"}
    summary = summarise(df)
    for scen in ("step", "random_steps"):
        ratios = summary["ratios"][scen]
        assert ratios["worst_ISE_ratio"] == pytest.approx(1.0, abs=1e-12)
        assert ratios["worst_ITAE_ratio"] == pytest.approx(1.0, abs=1e-12)
        assert ratios["worst_relative_ess_GC"] < 0.01
    assert all(v for v in summary["quality_bar"].values() if v is not None)
    side_by_side = recipes_markdown({"a": df, "b": df})
    assert "| ISE ratio a | ISE ratio b |" in side_by_side
    assert "| cstr | 1 | 1 | 1 | 1 |" in side_by_side  # ISE and ITAE ratios of both
    gc = trajs["sine"]["GC"]["cstr"]
    np.testing.assert_array_equal(gc.y, trajs["sine"]["LQI"]["cstr"].y)
    assert output_mse(RuntimeAdapter(LQIRuntime(PLANTS)), plants, duration=5.0) == {
        "cstr": 0.0,
        "hydraulic_actuator": 0.0,
    }


def test_lqi_through_the_evaluator_reproduces_the_data_stage(tiny_demos):
    """The evaluator's LQI run of a step equals the stored demonstration, sample by sample."""
    plants = [load_plant(n) for n in PLANTS]
    amp = float(tiny_demos.r[0, 0])
    name = str(tiny_demos.plant[0])
    duration = tiny_demos.r.shape[1] * tiny_demos.dt
    scen = {"step": {"kind": "step", "amplitude": amp, "duration": duration}}
    plant = next(p for p in plants if p.name == name)
    scen["step"]["amplitude"] = amp / plant.amplitude_scale
    _, trajs = evaluate(LQIRuntime(PLANTS), plants, scen)
    tr = trajs["step"]["LQI"][name]
    n = plant.order
    np.testing.assert_allclose(tr.u[0], tiny_demos.u[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(tr.x[0, :-1, :n], tiny_demos.x[0, :, :n], rtol=0, atol=1e-12)


def test_divergence_is_reported_as_such_never_averaged():
    plants = [load_plant(n) for n in PLANTS]
    bad = LQIRuntime(PLANTS, gain=-25.0)  # sign-flipped, amplified LQI: unstable loop
    df, _ = evaluate(bad, plants, {"step": SCENARIOS["step"]})
    gc = df[(df.controller == "GC") & (df.scenario == "step")]
    flags = gc[gc.metric == "diverged"].set_index("system")["value"]
    assert (flags == 1.0).all()
    assert gc[gc.metric == "ISE"]["value"].isna().all()  # no huge number to average
    summary = summarise(df)
    assert summary["diverged"]["GC"] == {"step": 2}
    assert summary["diverged"]["LQI"] == {}
    assert summary["quality_bar"]["stable_everywhere"] is False
    assert "diverged" in table2_markdown(df)
    assert "| cstr |" in table_all_markdown(df)


def _tiny_policy(tiny_data_dir: Path, out: Path, uri: str) -> Path:
    overrides = tiny_train_overrides(
        tiny_data_dir, out, uri, "logger.log_model=false", "model.hidden=8", "experts=2",
        f"closed_loop.systems=[{','.join(PLANTS)}]",
    )  # fmt: skip
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    metrics, objects = train(cfg)
    assert np.isfinite(metrics["closed_loop/mse/cstr"]) or metrics["closed_loop/diverged"] > 0
    return Path(objects["policy_path"])


def _evaluate_command(tmp_path: Path, *overrides: str) -> tuple[list[str], dict[str, str]]:
    """``python -m generalist_control.evaluate`` with ``overrides``, and its environment."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    return [sys.executable, "-m", "generalist_control.evaluate", *overrides], env


def _duration(run) -> int:
    return run.info.end_time - run.info.start_time


@pytest.mark.slow
def test_entry_point_writes_csv_tables_plots_and_logs_a_run_of_its_own(
    tiny_data_dir, tmp_path, mlflow_uri
):
    policy = _tiny_policy(tiny_data_dir, tmp_path, mlflow_uri)
    reports = tmp_path / "reports"
    cmd, env = _evaluate_command(
        tmp_path,
        f"policy={policy}",
        f"systems.include=[{','.join(PLANTS)}]",
        f"paths.reports_dir={reports}",
        f"logger.tracking_uri={mlflow_uri}",
        f"logger.experiment_name={tmp_path.name}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    mlflow.set_tracking_uri(mlflow_uri)
    (training,) = mlflow.search_runs(experiment_names=[tmp_path.name], output_format="list")
    proc = run_command(cmd, cwd=REPO, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"evaluation written to {reports}" in proc.stdout
    assert f"evaluation written to {reports}" in (tmp_path / "hydra" / "evaluate.log").read_text()

    df = pd.read_csv(reports / "metrics.csv")
    assert list(df.columns) == ["system", "scenario", "controller", "run", "metric", "value"]
    assert set(df.system) == set(PLANTS)
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        scenarios = set(compose("config").evaluation.scenarios)
    # every configured scenario that applies to these plants, plus nothing else
    expected = {s for s in scenarios if s not in ("saturation_0.5", "saturation_0.25")}
    assert set(df.scenario) == expected
    table = (reports / "table2.md").read_text()
    assert "| NMP | H.Act |" in table and "(GC) paper" in table and "(LQI) ours" in table
    summary = json.loads((reports / "summary.json").read_text())
    assert set(summary["quality_bar"]) == {
        "stable_everywhere", "ess_within_0.5pct", "ISE_ratio_le_1.05", "ITAE_ratio_le_1.25",
        "RMSE_ratio_le_1.1", "GC_AW_no_worse_than_LQI_AW",
    }  # fmt: skip
    # the set-point check: one row per plant, its verdict in the summary and in MLflow
    setpoint = pd.read_csv(reports / "setpoint.csv").set_index("system")
    assert set(setpoint.index) == set(PLANTS)
    assert (setpoint["radius_LQI"] < 1).all() and (setpoint["tail_error_LQI"] < 1e-3).all()
    unsettled = sorted(setpoint.index[~setpoint["settles"]])
    assert summary["setpoint"]["unsettled"] == unsettled
    assert summary["setpoint"]["n_systems"] == len(PLANTS)
    plots = {p.name for p in (reports / "plots").glob("*.png")}
    assert {"cstr_step_sine.png", "hydraulic_actuator_step_sine.png"} <= plots
    assert {"cstr_rate_limit_0.5.png", "cstr_noise_disturbance.png"} <= plots
    responses = pd.read_csv(reports / "responses.csv")
    assert {"system", "controller", "t", "y", "u"} <= set(responses.columns)

    # a run of its own, nested under the training run, which keeps its own duration
    runs = mlflow.search_runs(experiment_names=[tmp_path.name], output_format="list")
    (run,) = [r for r in runs if r.info.run_id != training.info.run_id]
    assert run.data.tags["mlflow.parentRunId"] == training.info.run_id
    assert run.data.tags["gc.source_run_id"] == training.info.run_id
    assert run.info.status == "FINISHED"
    assert "eval/diverged/GC" in run.data.metrics
    # the quality-bar verdicts as 0/1 metrics, for MLflow's Compare view
    measured = {k: v for k, v in summary["quality_bar"].items() if v is not None}
    for name, met in measured.items():
        assert run.data.metrics[f"eval/bar/{name}"] == float(met)
    assert run.data.metrics["eval/bar_passed"] == sum(measured.values())
    assert run.data.metrics["eval/bar_checked"] == len(measured)
    assert run.data.metrics["eval/setpoint/unsettled"] == len(unsettled)
    names = {a.path for a in mlflow.MlflowClient().list_artifacts(run.info.run_id, "eval")}
    assert "eval/metrics.csv" in names and "eval/table2.md" in names

    # the same policy through its MLflow URI gives the same closed loops
    proc = run_command(
        [*cmd[:3], f"policy=runs:/{training.info.run_id}", *cmd[4:-1],
         "evaluation.plots=false", f"hydra.run.dir={tmp_path / 'hydra2'}"],
        cwd=REPO, env=env, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    pd.testing.assert_frame_equal(pd.read_csv(reports / "metrics.csv"), df)
    assert not (reports / "plots").exists()
    after = mlflow.get_run(training.info.run_id)
    assert _duration(after) == _duration(training) and after.info.status == "FINISHED"
    evaluations = [r for r in mlflow.search_runs(experiment_names=[tmp_path.name],
                   output_format="list") if r.info.run_id != training.info.run_id]  # fmt: skip
    assert len(evaluations) == 2
    assert not [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name]


def test_a_failed_entry_point_says_why_and_writes_nothing(tmp_path):
    cmd, env = _evaluate_command(
        tmp_path,
        f"policy={tmp_path / 'missing.ckpt'}",
        f"paths.reports_dir={tmp_path / 'reports'}",
        f"logger.tracking_uri=sqlite:///{tmp_path / 'mlflow.db'}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    proc = run_command(cmd, cwd=REPO, env=env, timeout=300)
    assert proc.returncode == 1
    assert f"no policy at '{tmp_path / 'missing.ckpt'}'" in proc.stderr
    assert not (tmp_path / "reports").exists()
    assert not [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name]


def _closed_loop_score(controller, plants, duration: float) -> dict[str, float]:
    """A fresh score's verdict on ``controller`` (LQI simulated for it)."""
    return ClosedLoopScore(plants, duration=duration)(controller)


def test_closed_loop_score_is_zero_for_the_expert_and_one_for_divergence():
    plants = [load_plant(n) for n in PLANTS]
    assert _closed_loop_score(RuntimeAdapter(LQIRuntime(PLANTS)), plants, duration=4.0) == {
        "cstr": 0.0,
        "hydraulic_actuator": 0.0,
    }
    assert _closed_loop_score(
        RuntimeAdapter(LQIRuntime(PLANTS, gain=-25.0)), plants, duration=4.0
    ) == {
        "cstr": 1.0,
        "hydraulic_actuator": 1.0,
    }
    half = _closed_loop_score(RuntimeAdapter(LQIRuntime(PLANTS, gain=0.5)), plants, duration=4.0)
    assert all(0.0 < v < 1.0 for v in half.values())


def test_a_kept_score_simulates_lqi_once_and_scores_as_a_fresh_one(monkeypatch):
    plants = [load_plant(n) for n in PLANTS]
    score = ClosedLoopScore(plants, duration=4.0)
    calls: list[str] = []
    real = comparison.simulate_many

    def counted(runs, controller):
        calls.append(type(controller).__name__)
        return real(runs, controller)

    monkeypatch.setattr(comparison, "simulate_many", counted)
    for gain in (0.5, 1.3):
        kept = score(RuntimeAdapter(LQIRuntime(PLANTS, gain=gain)))
        calls_before = len(calls)
        fresh = _closed_loop_score(RuntimeAdapter(LQIRuntime(PLANTS, gain=gain)), plants,
                                   duration=4.0)  # fmt: skip
        assert kept == fresh and all(0.0 < v < 1.0 for v in kept.values())
        assert calls[calls_before:].count("PerPlantController") == 1  # the fresh one's own
    assert calls.count("PerPlantController") == 1 + 2  # the kept score's, once


def test_the_bar_counts_every_scenario_and_says_what_it_did_not_measure():
    """A GC divergence in a tracking scenario alone makes stable_everywhere false."""
    rows = []
    for ctrl in ("GC", "LQI"):
        for system in ("a", "b"):
            for metric, value in (("ISE", 1.0), ("ITAE", 1.0), ("rise_time", 1.0),
                                  ("relative_steady_state_error", 0.0)):  # fmt: skip
                rows.append((system, "step", ctrl, 0, metric, value))
            rows.append((system, "step", ctrl, 0, "diverged", 0.0))
            bad = ctrl == "GC" and system == "b"
            rows.append((system, "sine", ctrl, 0, "diverged", float(bad)))
            for metric in ("ISE", "ITAE", "RMSE"):
                rows.append((system, "sine", ctrl, 0, metric, np.nan if bad else 2.0))
    df = pd.DataFrame(rows, columns=["system", "scenario", "controller", "run", "metric", "value"])
    summary = summarise(df)
    assert summary["diverged"]["GC"] == {"sine": 1}
    bar = summary["quality_bar"]
    assert bar["stable_everywhere"] is False
    assert bar["ISE_ratio_le_1.05"] is True and bar["RMSE_ratio_le_1.1"] is True
    assert summary["tracking"]["sine"]["n_systems"] == 1  # the diverged plant has no ratio
    assert bar["GC_AW_no_worse_than_LQI_AW"] is None  # no anti-windup scenario ran
