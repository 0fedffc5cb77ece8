"""Runs that must not hurt each other or leak: issue 10, items 2, 4, 6 and 8.

* trainings started together on a fresh SQLite store (the schema is created under a lock);
* credentials in URLs never reach params, artifacts, Hydra's saved configs or the log;
* a resume from an incompatible checkpoint is refused before the finished run is touched;
* a training killed with SIGKILL leaves a run that the next training sets ``KILLED``;
* ``last.ckpt`` is the last finished epoch, so a resume logs no epoch twice;
* only the DVC stage writes the published ``models/``.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest
import torch
import yaml

from generalist_control.tracking import mlflow_utils
from helpers import compose_cfg, run_command, tiny_train_overrides, train

REPO = Path(__file__).resolve().parents[1]
SECRET = "hunter2"
#: Short trainings: no MLflow model, no DAgger, no closed-loop scoring after training.
QUICK = ("logger.log_model=false", "dagger=null", "closed_loop.systems=[]")


def _overrides(data_dir: Path, out: Path, uri: str, *extra: str) -> list[str]:
    """A tiny training with the default policy location (``paths.models_dir`` not given)."""
    base = [o for o in tiny_train_overrides(data_dir, out, uri) if "models_dir" not in o]
    return [*base, f"paths.published_dir={out / 'published'}", *QUICK, *extra]


def _without(overrides: list[str], *keys: str) -> list[str]:
    return [o for o in overrides if not o.startswith(tuple(f"{k}=" for k in keys))]


def _env() -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    return env


def _runs(uri: str, experiment: str) -> list:
    mlflow.set_tracking_uri(uri)
    return mlflow.search_runs(experiment_names=[experiment], output_format="list")


# --- item 2: concurrent starts on a fresh SQLite store ---------------------------------------


def _open_run(uri: str, barrier, worker: int) -> None:
    """One training's start: open a run in a store that may not exist yet."""
    if barrier is not None:
        barrier.wait(timeout=600)  # all workers touch the store at the same instant
    with mlflow_utils.mlflow_run({"tracking_uri": uri, "experiment_name": "race"}):
        mlflow.log_param("worker", worker)


@pytest.mark.slow
def test_trainings_started_together_share_a_fresh_sqlite_store(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(2)
    procs = [ctx.Process(target=_open_run, args=(uri, barrier, i)) for i in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=600)
    assert [p.exitcode for p in procs] == [0, 0]  # unlocked: "duplicate column name: step"
    _open_run(uri, None, 2)  # and the store works afterwards
    runs = _runs(uri, "race")
    assert sorted(r.data.params["worker"] for r in runs) == ["0", "1", "2"]
    assert {r.info.status for r in runs} == {"FINISHED"}
    assert (tmp_path / "mlflow.db.lock").is_file()


# --- item 4: credentials --------------------------------------------------------------------


def _files_with(root: Path, needle: bytes) -> list[str]:
    return [str(p) for p in root.rglob("*") if p.is_file() and needle in p.read_bytes()]


@pytest.mark.slow
def test_credentials_are_redacted_everywhere(tiny_data_dir, tmp_path):
    """A password in the tracking URI and in another URL of the config, typed as overrides."""
    db = tmp_path / "mlflow.db"
    secret_uri = f"sqlite:///{db}?password={SECRET}"  # a working store, with a password
    hydra_dir = tmp_path / "hydra"
    overrides = _without(
        _overrides(tiny_data_dir, tmp_path, "x"), "run_dir", "logger.tracking_uri"
    )
    overrides.append(f"logger.tracking_uri='{secret_uri}'")  # quoted: the URI holds an "="
    extra = [f"+logger.extra_uri=postgresql://gc:{SECRET}@db:5432/x", f"hydra.run.dir={hydra_dir}"]
    cmd = [sys.executable, "train.py", *overrides, *extra]
    proc = run_command(cmd, cwd=REPO, env=_env(), timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = proc.stdout + proc.stderr
    assert "password=***" in log and SECRET not in log  # the "MLflow run ..." line

    (run,) = _runs(f"sqlite:///{db}", tmp_path.name)
    # logger.* is no param (logger.params); the full config is the artifact resolved.yaml
    assert not [k for k in run.data.params if k.startswith("logger.")]
    assert not [v for v in {**run.data.params, **run.data.tags}.values() if SECRET in v]
    dst = str(tmp_path / "artifacts")
    artifacts = Path(mlflow.artifacts.download_artifacts(run_id=run.info.run_id, dst_path=dst))
    assert (artifacts / "config" / "hydra" / "overrides.yaml").is_file()
    resolved = yaml.safe_load((artifacts / "config" / "resolved.yaml").read_text())
    assert resolved["logger"]["tracking_uri"].endswith("?password=***")
    assert resolved["logger"]["extra_uri"] == "postgresql://gc:***@db:5432/x"
    assert _files_with(artifacts, SECRET.encode()) == []
    # Hydra's own copies in the run directory, its log file, and the store itself
    assert "gc:***@db" in (hydra_dir / ".hydra" / "overrides.yaml").read_text()
    assert _files_with(hydra_dir, SECRET.encode()) == []
    assert SECRET.encode() not in db.read_bytes()


# --- item 6: an incompatible resume ---------------------------------------------------------


@pytest.mark.slow
def test_an_incompatible_resume_is_refused_before_the_run_is_touched(
    tiny_data_dir, tmp_path, mlflow_uri
):
    first = compose_cfg(*_overrides(tiny_data_dir, tmp_path / "a", mlflow_uri, "model.hidden=16"))
    _, objs = train(first)
    last = tmp_path / "a" / "run" / "checkpoints" / "last.ckpt"
    resume = _overrides(
        tiny_data_dir, tmp_path / "b", mlflow_uri, "model.hidden=32", f"ckpt_path={last}"
    )
    with pytest.raises(ValueError, match=r"model\.hidden: checkpoint 16, config 32") as err:
        train(compose_cfg(*resume))
    assert "model.hidden=16" in str(err.value) and "drop ckpt_path" in str(err.value)
    # another plant set: refused, not trained on the checkpoint's plants
    other = _overrides(tiny_data_dir, tmp_path / "b", mlflow_uri, "model.hidden=16",
                       f"ckpt_path={last}", "systems.include=[cstr]")  # fmt: skip
    with pytest.raises(ValueError, match=r"trained on the plants \['cstr', 'hydraulic_actu"):
        train(compose_cfg(*other))
    # nothing left to train: refused, not 0 epochs and the old checkpoint published
    done = _overrides(tiny_data_dir, tmp_path / "b", mlflow_uri, "model.hidden=16",
                      f"ckpt_path={last}")  # fmt: skip
    with pytest.raises(ValueError, match="has finished 1 epochs and trainer.max_epochs is 1"):
        train(compose_cfg(*done))
    assert mlflow.get_run(objs["run_id"]).info.status == "FINISHED"
    assert len(_runs(mlflow_uri, "b")) == 0  # nothing was opened for the refused resumes
    assert not (tmp_path / "b" / "run").exists() or not list((tmp_path / "b").rglob("*.ckpt"))


def test_a_users_metrics_json_in_the_published_folder_is_not_overwritten(
    tiny_data_dir, tmp_path, mlflow_uri
):
    published = tmp_path / "mine"
    published.mkdir()
    (published / "metrics.json").write_text('{"my_score": 3}\n')
    cfg = compose_cfg(*_overrides(tiny_data_dir, tmp_path, mlflow_uri, "publish=true",
                                  f"paths.published_dir={published}"))  # fmt: skip
    with pytest.raises(FileExistsError, match=r"refusing to overwrite .*mine/metrics.json"):
        train(cfg)
    assert (published / "metrics.json").read_text() == '{"my_score": 3}\n'
    assert len(_runs(mlflow_uri, tmp_path.name)) == 0


# --- item 8: a killed training, last.ckpt, the published model ------------------------------


def _wait_for_epoch(uri: str, experiment: str, proc: subprocess.Popen, err: Path):
    """The subprocess's run once it has logged an epoch."""
    deadline = time.monotonic() + 500
    while time.monotonic() < deadline:
        assert proc.poll() is None, err.read_text()[-3000:]
        runs = _runs(uri, experiment)
        if runs and "train/loss" in runs[0].data.metrics:
            return runs[0]
        time.sleep(1)
    raise AssertionError("the training logged no epoch in time")


@pytest.mark.slow
def test_a_killed_training_is_set_killed_by_the_next_one(tiny_data_dir, tmp_path, mlflow_uri):
    long = ("trainer.max_epochs=1000", "callbacks.early_stopping.patience=1000")
    overrides = _overrides(tiny_data_dir, tmp_path, mlflow_uri, *long)
    cmd = [sys.executable, "train.py", *overrides, f"hydra.run.dir={tmp_path / 'hydra'}"]
    mlflow.MlflowClient(mlflow_uri).search_experiments()  # create the store before polling
    err = tmp_path / "stderr.txt"
    with open(err, "w") as stderr:
        proc = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdout=stderr, stderr=stderr)
    try:
        run = _wait_for_epoch(mlflow_uri, tmp_path.name, proc, err)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert mlflow.get_run(run.info.run_id).info.status == "RUNNING"  # nobody ended it

    second = _without(
        _overrides(tiny_data_dir, tmp_path / "next", mlflow_uri), "logger.experiment_name"
    )
    second.append(f"logger.experiment_name={tmp_path.name}")  # the killed run's experiment
    _, objs = train(compose_cfg(*second))
    killed = mlflow.get_run(run.info.run_id)
    assert killed.info.status == "KILLED"
    assert killed.data.tags["gc.pid"] == str(proc.pid) and killed.data.tags["gc.heartbeat"]
    assert f":{proc.pid} is gone" in killed.data.tags["gc.killed_reason"]
    assert mlflow.get_run(objs["run_id"]).info.status == "FINISHED"


@pytest.mark.slow
@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signalled_training_exits_non_zero_and_its_run_is_killed(
    tiny_data_dir, tmp_path, mlflow_uri, sig, status
):
    """SIGTERM and Ctrl-C: Lightning stops the fit by SystemExit(None or 1); the command
    must exit 128 + signal, its run KILLED, and write no policy (issue 51, defect 13)."""
    long = ("trainer.max_epochs=1000", "callbacks.early_stopping.patience=1000")
    overrides = _overrides(tiny_data_dir, tmp_path, mlflow_uri, *long)
    cmd = [sys.executable, "train.py", *overrides, f"hydra.run.dir={tmp_path / 'hydra'}"]
    mlflow.MlflowClient(mlflow_uri).search_experiments()  # create the store before polling
    err = tmp_path / "stderr.txt"
    with open(err, "w") as stderr:
        proc = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdout=stderr, stderr=stderr)
    try:
        run = _wait_for_epoch(mlflow_uri, tmp_path.name, proc, err)
        proc.send_signal(sig)
        assert proc.wait(timeout=120) == status, err.read_text()[-3000:]
    finally:
        proc.kill()
    assert mlflow.get_run(run.info.run_id).info.status == "KILLED"
    assert not list(tmp_path.rglob("policy.ckpt"))
    assert "KILLED, no policy written" in err.read_text()


@pytest.mark.slow
def test_last_checkpoint_is_the_last_epoch_so_a_resume_repeats_none(
    tiny_data_dir, tmp_path, mlflow_uri
):
    # lr 0: val/loss is the same every epoch, so only epoch 0 is ever a new best
    flat = ("optimizer.lr=0.0", "monitor=val/loss", "closed_loop_val=null")
    first = _overrides(tiny_data_dir, tmp_path / "a", mlflow_uri, *flat, "trainer.max_epochs=3")
    _, objs1 = train(compose_cfg(*first))
    ckpts = tmp_path / "a" / "run" / "checkpoints"
    assert sorted(p.name for p in ckpts.iterdir()) == ["best-epoch000.ckpt", "last.ckpt"]
    assert torch.load(ckpts / "last.ckpt", weights_only=True)["epoch"] == 2

    resume = _overrides(
        tiny_data_dir, tmp_path / "b", mlflow_uri, *flat, "trainer.max_epochs=4",
        f"ckpt_path={ckpts / 'last.ckpt'}",
    )  # fmt: skip
    _, objs2 = train(compose_cfg(*resume))
    assert objs2["run_id"] == objs1["run_id"]
    history = mlflow.MlflowClient().get_metric_history(objs2["run_id"], "val/loss")
    assert sorted(m.step for m in history) == [0, 1, 2, 3]  # each epoch logged once


@pytest.mark.slow
def test_only_the_dvc_stage_publishes_to_models(tiny_data_dir, tmp_path, mlflow_uri, caplog):
    published = tmp_path / "published" / "policy.ckpt"
    cfg = compose_cfg(*_overrides(tiny_data_dir, tmp_path, mlflow_uri))
    assert compose_cfg().paths.models_dir == "models"  # evaluate's default, the stage's output
    assert cfg.paths.models_dir == cfg.paths.published_dir
    caplog.set_level(logging.INFO, logger="generalist_control.training.fit")
    _, objs = train(cfg)
    own = tmp_path / "run" / "models" / "policy.ckpt"
    assert not published.exists() and Path(objs["policy_path"]) == own and own.is_file()
    assert mlflow.get_run(objs["run_id"]).data.tags["policy_dir"] == str(own.parent.resolve())
    assert f"policy written to {own}; MLflow run {objs['run_id']}" in caplog.text

    # the DVC stage's own command, its published_dir moved into tmp_path
    stage = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]["train"]
    words = shlex.split(stage["cmd"])
    words = words[words.index("python") :]  # after its `env` pins (tests/test_dvc.py's)
    assert words[:3] == ["python", "-m", "generalist_control.train"]
    assert "publish=true" in words and "paths.published_dir=models" in words
    assert "models/policy.ckpt" in stage["outs"]
    words = _without(words, "paths.published_dir") + [f"paths.published_dir={published.parent}"]
    overrides = _without(
        _overrides(tiny_data_dir, tmp_path / "stage", mlflow_uri), "paths.published_dir"
    )
    cmd = [sys.executable, *words[1:], *overrides, f"hydra.run.dir={tmp_path / 'hydra'}"]
    proc = run_command(cmd, cwd=REPO, env=_env(), timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert published.is_file() and (published.parent / "metrics.json").is_file()
    assert not (tmp_path / "stage" / "run" / "models").exists()
