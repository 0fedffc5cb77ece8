"""Grouped Hydra multiruns: one MLflow parent run per sweep, each job's run nested under it."""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import mlflow
import pytest
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf

from generalist_control.common.stop_signals import Stopped
from generalist_control.sweeps.hydra_callback import sweep_overrides
from generalist_control.tracking import mlflow_utils
from helpers import quick_overrides, run_command, sweep_callback

REPO = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for key in ("MLFLOW_TRACKING_URI", mlflow_utils.PARENT_RUN_ENV, mlflow_utils.SWEEP_ENV):
        env.pop(key, None)
    return env


@pytest.mark.slow
def test_multirun_makes_one_parent_with_a_child_per_point(tiny_data_dir, tmp_path, mlflow_uri):
    """`python train.py -m model.hidden=8,16` (tiny data, one epoch): 2 children, 1 parent.

    All in the experiment of kind sweep (``<prefix>/sweep``), none in train's.
    """
    sweep_dir = tmp_path / "multirun"
    cmd = [
        sys.executable,
        "train.py",
        "-m",
        "model.hidden=8,16",
        *quick_overrides(tiny_data_dir, tmp_path, mlflow_uri),
        "logger.experiment_name=null",
        f"++logger.experiment_prefix={tmp_path.name}",
        f"hydra.sweep.dir={sweep_dir}",
    ]
    proc = run_command(cmd, cwd=REPO, env=_env(), timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]

    mlflow.set_tracking_uri(mlflow_uri)
    assert mlflow.get_experiment_by_name(f"{tmp_path.name}/train") is None
    runs = mlflow.search_runs(experiment_names=[f"{tmp_path.name}/sweep"], output_format="list")
    parents = [r for r in runs if r.data.tags.get("gc.role") == "sweep"]
    children = [r for r in runs if r not in parents]
    (parent,) = parents
    assert len(children) == 2
    assert parent.info.status == "FINISHED"
    assert parent.info.run_name == "sweep:model.hidden=8,16"
    assert parent.data.metrics["sweep/n_runs"] == 2
    assert {c.data.params["model.hidden"] for c in children} == {"8", "16"}
    for child in children:
        assert child.info.status == "FINISHED"
        assert child.data.tags["mlflow.parentRunId"] == parent.info.run_id
        assert child.data.tags["sweep"] == parent.info.run_name
        # the closed-loop score of the ablation study rides on every sweep point
        assert {"closed_loop/mse/cstr", "closed_loop/mse_mean"} <= set(child.data.metrics)
    best = min(children, key=lambda c: c.data.metrics["best/val/loss"])
    assert parent.data.tags["sweep.best_run_id"] == best.info.run_id
    # each job keeps its model in its own directory, not in the DVC output models/
    for job in ("0", "1"):
        assert (sweep_dir / job / "models" / "policy.ckpt").is_file()
    models = {c.data.tags["policy_dir"] for c in children}
    assert models == {str(sweep_dir / "0" / "models"), str(sweep_dir / "1" / "models")}


def _sweep_config(tmp_path: Path, uri: str, job: str = "train"):
    return OmegaConf.create(
        {
            "hydra": {
                "job": {"name": job},
                "overrides": {"task": ["experts=1,3", "trainer.max_epochs=2"]},
                "sweep": {"dir": str(tmp_path / "multirun")},
                "sweeper": {"params": None},
            },
            "logger": {
                "tracking_uri": uri,
                "experiment_name": None,
                "experiment_prefix": tmp_path.name,
            },
            "optimized_metric": "val/loss",
        }
    )


def test_sweep_callback_parents_runs_and_ends_failed_on_a_failed_job(
    tmp_path, mlflow_uri, monkeypatch
):
    for key in (mlflow_utils.PARENT_RUN_ENV, mlflow_utils.SWEEP_ENV):
        monkeypatch.delenv(key, raising=False)
    cfg = _sweep_config(tmp_path, mlflow_uri)
    callback = sweep_callback()
    callback.on_multirun_start(cfg)
    parent_id = callback.run_id
    assert os.environ[mlflow_utils.PARENT_RUN_ENV] == parent_id
    client = mlflow.MlflowClient()
    exp_id = client.get_run(parent_id).info.experiment_id
    assert client.get_experiment(exp_id).name == f"{tmp_path.name}/sweep"
    # a job's training run: in its parent's experiment, tagged from the environment
    child_id = client.create_run(exp_id, tags=mlflow_utils.parent_run_tags()).info.run_id
    client.log_metric(child_id, "best/val/loss", 0.5)
    client.set_terminated(child_id)
    callback.on_job_end(cfg, JobReturn(status=JobStatus.COMPLETED))
    callback.on_job_end(cfg, JobReturn(status=JobStatus.FAILED))
    callback.on_multirun_end(cfg)

    parent, child = client.get_run(parent_id), client.get_run(child_id)
    assert child.data.tags["mlflow.parentRunId"] == parent_id
    assert child.data.tags["sweep"] == "sweep:experts=1,3"
    assert parent.info.status == "FAILED"  # one job failed
    assert parent.data.tags["sweep.best_run_id"] == child_id
    assert parent.data.metrics["sweep/best/val/loss"] == pytest.approx(0.5)
    assert mlflow_utils.PARENT_RUN_ENV not in os.environ  # restored after the sweep
    assert mlflow_utils.parent_run_tags() == {}  # a later plain run has no parent


def test_sweep_callback_ignores_other_entry_points(tmp_path, mlflow_uri):
    callback = sweep_callback(jobs=["train"])
    callback.on_multirun_start(_sweep_config(tmp_path, mlflow_uri, job="generate"))
    assert callback.run_id is None
    assert mlflow_utils.PARENT_RUN_ENV not in os.environ


def test_sweep_overrides_keeps_only_sweeping_ones():
    given = ["model.hidden=16,32,64", "experts=range(1,6,2)", "seed=1", "+x=choice(a,b)"]
    assert sweep_overrides(given) == [given[0], given[1], given[3]]


def test_a_signal_stops_the_sweep_and_ends_its_parent_killed(tmp_path, mlflow_uri):
    """SIGTERM in the launching process: an interrupt there (no next job), the parent and
    the runs of its jobs whose process is gone KILLED at exit, the handlers restored."""
    before = signal.getsignal(signal.SIGTERM)
    cfg = _sweep_config(tmp_path, mlflow_uri)
    callback = sweep_callback()
    callback.on_multirun_start(cfg)
    client = mlflow.MlflowClient()
    exp_id = client.get_run(callback.run_id).info.experiment_id
    # a job's run whose worker the launcher killed (a pid that is no process)
    tags = {**mlflow_utils.parent_run_tags(), **mlflow_utils.process_tags()}
    tags[mlflow_utils.PID_TAG] = str(2**22 + 7)
    orphan = client.create_run(exp_id, tags=tags).info.run_id
    parent_id = callback.run_id
    with pytest.raises(Stopped, match="stopped by SIGTERM"):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises here
    callback._end_at_exit()  # what atexit runs as the process ends
    assert client.get_run(parent_id).info.status == "KILLED"
    assert client.get_run(orphan).info.status == "KILLED"
    assert signal.getsignal(signal.SIGTERM) is before
