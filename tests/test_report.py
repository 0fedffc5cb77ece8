"""The ablation report on synthetic MLflow runs: figures, missing points, no runs, gates."""

from __future__ import annotations

from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from matplotlib.text import Text

from ablation_runs import CONFIGS, PLANTS, log_runs, policy_meta
from generalist_control.common.paths import conf_dir
from generalist_control.evaluation.eval_run import RUN_TYPE_TAG
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.report import read_job, run
from generalist_control.reports.figures import FIGURES, figure_key, read_tables
from generalist_control.reports.gates import gate_weights
from generalist_control.reports.runs import NoAblationRunsError, RunPoint, select_sweeps
from generalist_control.reports.selection import MixedRunsError
from helpers import net_config


def _cfg(uri: str, experiment: str | None, out: Path, *extra: str):
    """The report's config; ``experiment`` None: the scheme, with prefix ``out.name``."""
    if experiment is None:
        where = ["logger.experiment_name=null", f"++logger.experiment_prefix={out.name}"]
    else:
        where = [f"logger.experiment_name={experiment}"]
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return compose(
            "config",
            overrides=[
                f"logger.tracking_uri={uri}",
                *where,
                f"logger.artifact_location={out / 'mlruns'}",
                f"report.out_dir={out / 'ablation'}",
                f"paths.reports_dir={out / 'eval'}",
                f"report.plants=[{','.join(PLANTS)}]",
                "report.gate.duration=2.0",
                *extra,
            ],
        )


def _texts(name: str, folder: Path) -> list[str]:
    """Every text a report figure shows (titles, labels, legend, annotations)."""
    fig = FIGURES[name](read_tables(folder))
    return [t.get_text() for t in fig.findobj(Text) if t.get_text()]


def test_report_from_runs(tmp_path, mlflow_uri):
    ids = log_runs(mlflow_uri, tmp_path.name, tmp_path)
    summary = run(_cfg(mlflow_uri, tmp_path.name, tmp_path))
    out = tmp_path / "ablation"

    names = [*(f"{k}_{s}" for s in ("hidden", "experts") for k in ("mse", "loss")),
             "params_vs_mse", "gate_weights"]  # fmt: skip
    key = read_tables(out).key
    for name in names:  # drawn from the tables it wrote, as `make results` draws them
        assert figure_key(out / f"{name}.png") == key
    assert not list(tmp_path.glob(".ablation.*"))  # the staging directory is gone

    assert summary["missing"] == ["d=16"]
    assert summary["points"]["hidden"]["d=64"] == ids[(64, 3)]
    assert summary["gate_run"] == ids[(32, 5)]

    runs = pd.read_csv(out / "runs.csv").set_index("label")
    assert runs.loc["d=16", "status"] == "no run" and pd.isna(runs.loc["d=16", "run_id"])
    assert runs.loc["M=5", "run_id"] == ids[(32, 5)]
    points = pd.read_csv(out / "points.csv").set_index("run")
    assert points.loc["d32-M1", "mse/double_integrator"] == pytest.approx(1e-2)
    assert pd.isna(points.loc["d32-M1", "mse/cstr"])  # diverged: no score
    assert points.loc["d32-M5", "final_train_loss"] == pytest.approx(6e-4)
    mse = _texts("mse_experts", out)
    assert "Closed-loop output MSE by M" in mse and "no score" in mse  # M=1 on cstr
    assert {"M=1", "M=3", "M=5"} <= set(mse)
    assert {"d=32", "d=64"} <= set(_texts("mse_hidden", out))  # d=16 has no run: left out
    assert not any("no run" in t for n in names for t in _texts(n, out))

    gates = pd.read_csv(out / "gate_weights.csv", index_col="plant")
    assert list(gates.index) == sorted(PLANTS, key=lambda p: load_plant(p).tag)
    assert gates.shape[1] == 5
    np.testing.assert_allclose(gates.sum(axis=1), 1.0, rtol=1e-5)

    text = (out / "comparison.md").read_text()
    assert "| final training loss, d=16, M=3 | 1.02e-02 | no run: d=16, M=3 | no run |" in text
    # fake runs of the default recipe: its losses and counts are not the paper's units
    assert (
        "| final training loss, d=32, M=3 | 9.43e-04 | 9.00e-04 (run) | not comparable |" in text
    )
    assert "| parameters, d=32, M=3 | 59,180 |" in text
    assert (
        "| crazyflie_altitude output MSE, d=32, M=3 | 5.90e-02 | no score (run) | no score |"
        in text
    )
    # 6e-4 / 9e-4 against the paper's 5.87e-4 / 9.43e-4, within a factor 2
    row = '| training loss M=5 over M=3 ("marginal improvement") | 0.622 | 0.667 (run) |'
    assert row + " reproduces |" in text

    # the report run: tagged, with the artifacts; a second report leaves it out of the search
    client = mlflow.MlflowClient(mlflow_uri)
    report = client.get_run(summary["report_run_id"])
    assert report.data.tags[RUN_TYPE_TAG] == "report"
    assert report.data.metrics["report/missing_points"] == 1.0
    assert report.data.metrics["ablation/final_train_loss/d32_M3"] == pytest.approx(9e-4)
    names = {a.path for a in client.list_artifacts(report.info.run_id, "ablation")}
    assert "ablation/comparison.md" in names and "ablation/gate_weights.png" in names
    again = run(_cfg(mlflow_uri, tmp_path.name, tmp_path, "report.log_mlflow=false"))
    assert again["points"] == summary["points"]


def test_no_runs_is_an_error_naming_the_sweeps(tmp_path, mlflow_uri):
    cfg = _cfg(mlflow_uri, f"{tmp_path.name}-empty", tmp_path)
    with pytest.raises(NoAblationRunsError, match=r"python train\.py -m model\.hidden=16,32,64"):
        run(cfg)
    assert not (tmp_path / "ablation").exists()


def test_runs_off_both_sweeps_give_a_report_of_missing_points(tmp_path, mlflow_uri):
    mlflow.set_tracking_uri(mlflow_uri)
    exp_id = mlflow.create_experiment(tmp_path.name)
    with mlflow.start_run(experiment_id=exp_id):
        mlflow.log_params({"model.hidden": 8, "experts": 2, "n_parameters": 1000})
        mlflow.log_metric("train/loss", 0.5, step=0)
    summary = run(_cfg(mlflow_uri, tmp_path.name, tmp_path, "report.log_mlflow=false"))
    assert len(summary["missing"]) == 6 and summary["gate_run"] is None
    assert not list((tmp_path / "ablation").glob("*.png"))  # nothing to draw: no placeholder
    text = (tmp_path / "ablation" / "comparison.md").read_text()
    assert "| final training loss, d=32, M=3 | 9.43e-04 | no run: d=32, M=3 | no run |" in text


def test_newest_run_of_a_configuration_wins():
    def point(run_id, d, m, t):
        return RunPoint(run_id, run_id, d, m, 1, 0.1, start_time=t)

    points = [point("old", 32, 3, 1), point("new", 32, 3, 2), point("m5", 32, 5, 3)]
    sweeps = select_sweeps(points, (16, 32), (3, 5), (32, 3))
    assert sweeps["hidden"] == {16: None, 32: points[1]}
    assert sweeps["experts"] == {3: points[1], 5: points[2]}


def test_the_settings_are_read_once_and_checked():
    job = read_job(_cfg("sqlite://", "x", Path("out"), "report.parent_run=ablation:paper"))
    assert job.report.parent_run == ("ablation:paper",) and job.report.baseline.hidden == 32
    assert job.plants == tuple(PLANTS) and job.bar["ISE_ratio"] == 1.05
    with pytest.raises(ValueError, match=r"report\.gate\.experts must be an integer"):
        read_job(_cfg("sqlite://", "x", Path("out"), "report.gate.experts=5.5"))
    with pytest.raises(ValueError, match=r"report has unknown keys \['colour'\]"):
        read_job(_cfg("sqlite://", "x", Path("out"), "+report.colour=red"))


def test_gate_weights_follow_the_plants_asked_for():
    policy = Policy(net_config(hidden=16, experts=3, heads=2))
    gates = gate_weights(policy, policy_meta(), ["cstr"], duration=1.0)
    assert list(gates.index) == ["cstr"] and list(gates.columns) == [
        "expert_1",
        "expert_2",
        "expert_3",
    ]
    assert gates.to_numpy().sum() == pytest.approx(1.0, rel=1e-5)
    with pytest.raises(KeyError, match="not trained on"):
        gate_weights(policy, policy_meta(), ["boeing747"])


def test_study_trials_and_parents_are_left_out(tmp_path, mlflow_uri):
    from generalist_control.reports.runs import runs_from_mlflow

    mlflow.set_tracking_uri(mlflow_uri)
    exp_id = mlflow.create_experiment(tmp_path.name)
    kept = {}
    for role in ("sweep", "study"):
        with mlflow.start_run(experiment_id=exp_id, tags={"gc.role": role}) as parent:
            with mlflow.start_run(experiment_id=exp_id, nested=True) as child:
                mlflow.log_params({"model.hidden": 32, "experts": 3})
                kept[role] = child.info.run_id
            mlflow.log_params({"model.hidden": 32, "experts": 3})  # even with params
        assert parent.info.run_id
    points = runs_from_mlflow(tmp_path.name, client=mlflow.MlflowClient(mlflow_uri))
    assert [p.run_id for p in points] == [kept["sweep"]]


# ------------------------------------------------------------ runs of different budgets
#: One budget for every point, but the M=5 run trained twice as long.
TWO_BUDGETS = {
    **{point: {"trainer.max_epochs": 1, "run_dir": f"/runs/{point}"} for point in CONFIGS},
    (32, 5): {"trainer.max_epochs": 2, "run_dir": "/runs/other"},
}


def test_report_refuses_runs_of_two_budgets_naming_them(tmp_path, mlflow_uri):
    ids = log_runs(mlflow_uri, tmp_path.name, tmp_path, params=TWO_BUDGETS)
    with pytest.raises(MixedRunsError) as err:
        run(_cfg(mlflow_uri, tmp_path.name, tmp_path))
    text = str(err.value)
    assert "trainer.max_epochs:" in text
    assert f"'2' in d32-M5 ({ids[(32, 5)]})" in text
    for d, m in [(32, 3), (64, 3), (32, 1)]:
        assert f"d{d}-M{m} ({ids[(d, m)]})" in text
    assert "'1' in" in text
    assert "run_dir" not in text  # an identity key may differ
    assert "report.parent_run=" in text and "report.allow_mixed=true" in text
    assert "params.`trainer.max_epochs` = '1'" in text  # a filter_string that would do
    assert not (tmp_path / "ablation").exists()  # nothing written

    # the filter the message suggests gives a report of the 1-epoch runs only
    good = "report.filter_string=\"params.`trainer.max_epochs` = '1'\""
    summary = run(_cfg(mlflow_uri, tmp_path.name, tmp_path, good, "report.log_mlflow=false"))
    assert summary["points"]["experts"]["M=5"] is None and "mixed" not in summary


def test_a_param_logged_by_one_run_only_is_a_difference(tmp_path, mlflow_uri):
    extra = {(32, 5): {"dagger.enabled": "false"}}
    ids = log_runs(mlflow_uri, tmp_path.name, tmp_path, params=extra)
    with pytest.raises(MixedRunsError, match=r"dagger\.enabled: '\(not logged\)' in") as err:
        run(_cfg(mlflow_uri, tmp_path.name, tmp_path, "report.log_mlflow=false"))
    assert f"'false' in d32-M5 ({ids[(32, 5)]})" in str(err.value)


def test_allow_mixed_reports_with_a_warning_naming_the_runs(tmp_path, mlflow_uri, caplog):
    ids = log_runs(mlflow_uri, tmp_path.name, tmp_path, params=TWO_BUDGETS)
    with caplog.at_level("WARNING", logger="generalist_control.reports.selection"):
        summary = run(_cfg(mlflow_uri, tmp_path.name, tmp_path, "report.allow_mixed=true"))
    warned = "\n".join(r.getMessage() for r in caplog.records if r.levelname == "WARNING")
    assert "MIXED RUNS" in warned and "trainer.max_epochs" in warned
    assert f"d32-M5 ({ids[(32, 5)]})" in warned and f"d32-M3 ({ids[(32, 3)]})" in warned
    assert summary["mixed"]["trainer.max_epochs"]["2"] == [ids[(32, 5)]]
    assert summary["points"]["experts"]["M=5"] == ids[(32, 5)]
    report = mlflow.MlflowClient(mlflow_uri).get_run(summary["report_run_id"])
    assert ids[(32, 5)] in report.data.tags["report.mixed_params"]


def test_parent_run_selects_one_sweep(tmp_path, mlflow_uri):
    """A 1-epoch sweep and, outside it, a newer 2-epoch run of M=5: the sweep is reported."""
    mlflow.set_tracking_uri(mlflow_uri)
    exp_id = mlflow.create_experiment(tmp_path.name)
    client = mlflow.MlflowClient(mlflow_uri)
    sweep = client.create_run(exp_id, run_name="sweep:experts=1,3,5", tags={"gc.role": "sweep"})
    parent_id = sweep.info.run_id
    one_epoch = {point: {"trainer.max_epochs": 1} for point in CONFIGS}
    ids = log_runs(mlflow_uri, tmp_path.name, tmp_path, params=one_epoch, parent=parent_id)
    client.set_terminated(parent_id)
    adhoc = log_runs(
        mlflow_uri,
        tmp_path.name,
        tmp_path,
        params={(32, 5): {"trainer.max_epochs": 2}},
        configs={(32, 5): CONFIGS[(32, 5)]},
    )
    with pytest.raises(MixedRunsError, match=parent_id):  # the fix names the sweep
        run(_cfg(mlflow_uri, tmp_path.name, tmp_path, "report.log_mlflow=false"))
    for chosen in (parent_id, "sweep:experts=1,3,5"):
        extra = (f"report.parent_run='{chosen}'", "report.log_mlflow=false")
        summary = run(_cfg(mlflow_uri, tmp_path.name, tmp_path, *extra))
        assert summary["points"]["experts"]["M=5"] == ids[(32, 5)] != adhoc[(32, 5)]
    with pytest.raises(LookupError, match=r"'sweep:nothing' is no sweep.*" + parent_id):
        run(_cfg(mlflow_uri, tmp_path.name, tmp_path, "report.parent_run='sweep:nothing'"))


def test_report_reads_the_sweep_experiment_and_logs_to_the_report_one(tmp_path, mlflow_uri):
    prefix = tmp_path.name
    ids = log_runs(mlflow_uri, f"{prefix}/sweep", tmp_path)
    log_runs(mlflow_uri, f"{prefix}/train", tmp_path, params=TWO_BUDGETS)  # not read
    summary = run(_cfg(mlflow_uri, None, tmp_path))
    assert summary["points"]["experts"]["M=5"] == ids[(32, 5)]
    client = mlflow.MlflowClient(mlflow_uri)
    report = client.get_run(summary["report_run_id"])
    assert client.get_experiment(report.info.experiment_id).name == f"{prefix}/report"
    assert report.data.tags["report.source_experiment"] == f"{prefix}/sweep"
