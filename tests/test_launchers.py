"""Parallel Hydra launchers: a multirun's points at once, still under one MLflow parent run.

``hydra/launcher=parallel`` (hydra-joblib-launcher, two worker processes) and
``submitit_local`` (hydra-submitit-launcher's local executor, one process per job) run real
tiny trainings; the parent run reaches each job through the callback that Hydra pickles
into it (:meth:`MLflowSweepCallback.on_job_start`), whatever environment the job's process
inherited. ``named_parent`` groups separate commands (the DVC ablation's trainings).
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import time
from contextlib import nullcontext
from pathlib import Path

import mlflow
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf

from generalist_control.common.paths import conf_dir
from generalist_control.tracking import mlflow_utils, parents
from helpers import quick_overrides, run_command, sweep_callback

REPO = Path(__file__).resolve().parents[1]
ENV_KEYS = (mlflow_utils.PARENT_RUN_ENV, mlflow_utils.SWEEP_ENV)


def _env() -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": f"{REPO / 'src'}:{REPO}"}
    for key in ("MLFLOW_TRACKING_URI", *ENV_KEYS):
        env.pop(key, None)
    return env


def _multirun(tmp_path: Path, data_dir: Path, uri: str, *extra: str) -> list:
    """``python train.py -m model.hidden=8,16 <extra>``; the runs of its sweep experiment."""
    cmd = [
        sys.executable, "train.py", "-m", "model.hidden=8,16",
        *quick_overrides(data_dir, tmp_path, uri),
        "logger.experiment_name=null", f"++logger.experiment_prefix={tmp_path.name}",
        f"hydra.sweep.dir={tmp_path / 'multirun'}", *extra,
    ]  # fmt: skip
    proc = run_command(cmd, cwd=REPO, env=_env(), timeout=540)
    assert proc.returncode == 0, proc.stderr[-3000:]
    mlflow.set_tracking_uri(uri)
    return mlflow.search_runs(experiment_names=[f"{tmp_path.name}/sweep"], output_format="list")


def _family(runs: list) -> tuple:
    """The one parent and its children, each child nested under it."""
    (parent,) = [r for r in runs if r.data.tags.get("gc.role") == "sweep"]
    children = [r for r in runs if r is not parent]
    assert parent.info.status == "FINISHED"
    for child in children:
        assert child.info.status == "FINISHED"
        assert child.data.tags["mlflow.parentRunId"] == parent.info.run_id
        assert child.data.tags["sweep"] == parent.info.run_name
    return parent, children


@pytest.mark.slow
def test_parallel_launcher_trains_two_points_at_once_under_one_parent(
    tiny_data_dir, tmp_path, mlflow_uri
):
    # six short epochs each: long enough that two runs started together overlap clearly
    runs = _multirun(tmp_path, tiny_data_dir, mlflow_uri, "hydra/launcher=parallel",
                     "trainer.max_epochs=6")  # fmt: skip
    parent, children = _family(runs)
    assert len(children) == 2 and parent.data.metrics["sweep/n_runs"] == 2
    assert {c.data.params["model.hidden"] for c in children} == {"8", "16"}
    pids = {c.data.tags[mlflow_utils.PID_TAG] for c in children}
    assert len(pids) == 2 and str(os.getpid()) not in pids  # two worker processes
    starts = [c.info.start_time for c in children]
    ends = [c.info.end_time for c in children]
    overlap_ms = min(ends) - max(starts)
    print(f"the two trainings ran together for {overlap_ms / 1000:.1f} s of "
          f"{(max(ends) - min(starts)) / 1000:.1f} s")  # fmt: skip
    assert overlap_ms > 0, (starts, ends)


@pytest.mark.slow
def test_submitit_local_launcher_nests_its_jobs(tiny_data_dir, tmp_path, mlflow_uri):
    runs = _multirun(
        tmp_path, tiny_data_dir, mlflow_uri, "hydra/launcher=submitit_local",
        "hydra.launcher.timeout_min=10", "trainer.max_epochs=1",
    )  # fmt: skip
    parent, children = _family(runs)
    assert len(children) == 2
    assert len({c.data.tags[mlflow_utils.PID_TAG] for c in children}) == 2
    assert (tmp_path / "multirun" / ".submitit").is_dir()  # submitit's own job folders


def _session(sid: int) -> list[int]:
    """The processes of session ``sid`` (a command started in a session of its own)."""
    out = subprocess.run(["ps", "-o", "pid=", "-s", str(sid)], capture_output=True, text=True)
    return [int(pid) for pid in out.stdout.split()]


@pytest.mark.slow
def test_sigterm_stops_a_joblib_sweep(tiny_data_dir, tmp_path, mlflow_uri):
    """SIGTERM to ``train.py -m ... hydra/launcher=parallel`` while its first points train:
    a non-zero exit, no worker left, no further point started, the runs and parent KILLED."""
    cmd = [
        sys.executable, "train.py", "-m", "model.hidden=8,16,24",  # two at a time: 24 waits
        *quick_overrides(tiny_data_dir, tmp_path, mlflow_uri),
        "logger.experiment_name=null", f"++logger.experiment_prefix={tmp_path.name}",
        f"hydra.sweep.dir={tmp_path / 'multirun'}", "hydra/launcher=parallel",
        "trainer.max_epochs=1000", "~callbacks.early_stopping",  # would train for an hour
    ]  # fmt: skip
    log = tmp_path / "sweep.log"
    with log.open("w") as out:
        proc = subprocess.Popen(
            cmd, cwd=REPO, env=_env(), stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip
    try:
        deadline = time.monotonic() + 240
        while "MLflow run" not in log.read_text() and time.monotonic() < deadline:
            assert proc.poll() is None, log.read_text()[-3000:]
            time.sleep(0.5)
        assert len(_session(proc.pid)) > 2  # the workers run
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=120) != 0
        for _ in range(20):  # the killed workers may take a moment to go
            if not _session(proc.pid):
                break
            time.sleep(0.5)
        assert _session(proc.pid) == [], "processes left behind"
    finally:
        for pid in _session(proc.pid):
            os.kill(pid, signal.SIGKILL)
    text = log.read_text()
    assert "Stopped: stopped by SIGTERM" in text
    mlflow.set_tracking_uri(mlflow_uri)
    runs = mlflow.search_runs(experiment_names=[f"{tmp_path.name}/sweep"], output_format="list")
    (parent,) = [r for r in runs if r.data.tags.get("gc.role") == "sweep"]
    children = [r for r in runs if r is not parent]
    assert parent.info.status == "KILLED"
    assert children and {c.info.status for c in children} <= {"KILLED", "FAILED"}
    assert "24" not in {c.data.params.get("model.hidden") for c in children}


def _cfg(tmp_path: Path, uri: str):
    return OmegaConf.create(
        {
            "hydra": {
                "job": {"name": "train"},
                "overrides": {"task": ["model.hidden=8,16"]},
                "sweep": {"dir": str(tmp_path / "multirun")},
            },
            "logger": {"tracking_uri": uri, "experiment_name": tmp_path.name},
            "optimized_metric": "val/loss",
        }
    )


def test_the_parent_reaches_a_job_whose_process_did_not_inherit_it(
    tmp_path, mlflow_uri, monkeypatch
):
    """A loky worker reused from an earlier multirun has that one's environment."""
    for key in ENV_KEYS:
        monkeypatch.delenv(key, raising=False)
    cfg = _cfg(tmp_path, mlflow_uri)
    callback = sweep_callback()
    callback.on_multirun_start(cfg)
    parent_id = callback.run_id
    shipped = pickle.dumps(callback)  # as Hydra's launchers ship the callbacks to a job
    monkeypatch.setenv(mlflow_utils.PARENT_RUN_ENV, "an-earlier-sweeps-parent")
    in_job = pickle.loads(shipped)
    in_job.on_job_start(cfg)
    assert os.environ[mlflow_utils.PARENT_RUN_ENV] == parent_id
    assert mlflow_utils.parent_run_tags() == {
        "mlflow.parentRunId": parent_id,
        "sweep": "sweep:model.hidden=8,16",
    }
    in_job.on_job_end(cfg, JobReturn(status=JobStatus.COMPLETED))
    assert os.environ[mlflow_utils.PARENT_RUN_ENV] == "an-earlier-sweeps-parent"
    callback.on_multirun_end(cfg)
    assert mlflow.MlflowClient().get_run(parent_id).info.status == "FINISHED"


def test_a_group_files_separate_single_runs_under_one_parent(tmp_path, mlflow_uri, monkeypatch):
    for key in ENV_KEYS:
        monkeypatch.delenv(key, raising=False)
    cfg = _cfg(tmp_path, mlflow_uri)
    ids = []
    for _ in range(2):  # two commands, e.g. two DVC stages
        callback = sweep_callback(group="ablation:default")
        callback.on_run_start(cfg)
        callback.on_job_start(cfg)
        ids.append(os.environ[mlflow_utils.PARENT_RUN_ENV])
        assert os.environ[mlflow_utils.SWEEP_ENV] == "ablation:default"
        callback.on_job_end(cfg, JobReturn(status=JobStatus.COMPLETED))
        callback.on_run_end(cfg)
        assert mlflow_utils.PARENT_RUN_ENV not in os.environ
    assert ids[0] == ids[1]
    parent = mlflow.MlflowClient().get_run(ids[0])
    assert parent.info.run_name == "ablation:default" and parent.info.status == "FINISHED"
    assert parent.data.tags["gc.role"] == "group"
    assert mlflow.get_experiment(parent.info.experiment_id).name == tmp_path.name
    # a multirun ignores the group: its own parent, named after the sweep
    sweep = sweep_callback(group="ablation:default")
    sweep.on_multirun_start(cfg)
    assert sweep.run_id != ids[0]
    sweep.on_multirun_end(cfg)


def test_two_commands_that_both_create_the_group_keep_the_older(tmp_path, mlflow_uri, monkeypatch):
    """On a server store (no file lock) two commands may both create it: one survives."""
    logger = {"tracking_uri": mlflow_uri, "experiment_name": tmp_path.name}
    first = parents.named_parent(logger, "ablation:paper")
    time.sleep(0.05)  # the second is younger by its start time
    monkeypatch.setattr(mlflow_utils, "store_lock", lambda uri: nullcontext())
    calls = []
    real = parents._named

    def unseen_once(client, exp_id, name):  # the other command's run is not visible yet
        calls.append(name)
        return [] if len(calls) == 1 else real(client, exp_id, name)

    monkeypatch.setattr(parents, "_named", unseen_once)
    assert parents.named_parent(logger, "ablation:paper") == first
    client = mlflow.MlflowClient()
    exp_id = client.get_run(first).info.experiment_id
    alive = client.search_runs([exp_id], "attributes.run_name = 'ablation:paper'")
    assert [r.info.run_id for r in alive] == [first]  # the second one was deleted
    with pytest.raises(ValueError, match="letters, digits"):
        parents.named_parent(logger, "it's")


def test_launcher_configs_compose():
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        par = compose("config", ["hydra/launcher=parallel"], return_hydra_config=True)
        job = compose("config", ["hydra/launcher=joblib"], return_hydra_config=True)
        slurm = compose(
            "config",
            ["hydra/launcher=slurm", "hydra.launcher.partition=cpu"],
            return_hydra_config=True,
        )
    assert par.hydra.launcher.n_jobs == 2 and job.hydra.launcher.n_jobs == -1
    assert par.hydra.launcher._target_ == job.hydra.launcher._target_
    assert slurm.hydra.launcher._target_.endswith("submitit_launcher.SlurmLauncher")
    assert slurm.hydra.launcher.partition == "cpu" and slurm.hydra.launcher.timeout_min == 120
