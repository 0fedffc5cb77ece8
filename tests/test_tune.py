"""The Optuna study of tune.py: pruning, resuming, two PostgreSQL workers, a killed worker."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import mlflow
import optuna
import pytest
import sqlalchemy
from omegaconf import OmegaConf
from optuna.trial import TrialState

from generalist_control.sweeps.search_settings import (
    CHANGES_ATTR,
    FIXED_ATTR,
    StudyConfigChangedError,
    parse_space,
)
from generalist_control.sweeps.storage import open_storage
from generalist_control.sweeps.study import PARENT_ATTR
from generalist_control.tracking import mlflow_utils
from generalist_control.tune import run
from helpers import compose_cfg, quick_overrides
from pg import create_database

REPO = Path(__file__).resolve().parents[1]
#: A small space: the tiny data trains in about a second per trial.
SMALL_SPACE = (
    "hparams_search.params.model.hidden.choices=[8,16]",
    "hparams_search.params.experts.choices=[1,3]",
)


def _tune_overrides(data_dir: Path, out: Path, mlflow_uri: str, storage: str, *extra: str):
    return [
        *quick_overrides(data_dir, out, mlflow_uri),
        f"hparams_search.storage={storage}",
        f"hparams_search.trials_dir={out / 'trials'}",
        "hparams_search.study_name=tiny",
        *SMALL_SPACE,
        *extra,
    ]


def _cfg(*overrides: str):
    return compose_cfg("hparams_search=default", *overrides)


def _env() -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for key in ("MLFLOW_TRACKING_URI", mlflow_utils.PARENT_RUN_ENV, mlflow_utils.SWEEP_ENV):
        env.pop(key, None)
    return env


def _worker(overrides: list[str], hydra_dir: Path) -> subprocess.Popen:
    """``python tune.py <overrides>`` in the repository."""
    cmd = [sys.executable, "tune.py", *overrides, f"hydra.run.dir={hydra_dir}"]
    return subprocess.Popen(
        cmd, cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


def _runs(uri: str, experiment: str) -> list:
    mlflow.set_tracking_uri(uri)
    return mlflow.search_runs(experiment_names=[experiment], output_format="list")


# --------------------------------------------------------------------------- bad input
def test_unknown_search_key_is_named_with_a_suggestion(tmp_path):
    storage = tmp_path / "optuna.db"
    cfg = _cfg(
        f"hparams_search.storage=sqlite:///{storage}",
        "+hparams_search.params.model.hiden={type:int,low:8,high:16}",
    )
    with pytest.raises(KeyError, match=r"unknown search-space key 'model\.hiden'.*model\.hidden"):
        run(cfg)
    assert not storage.exists()  # checked before the storage is touched
    tree = OmegaConf.to_container(cfg)
    with pytest.raises(ValueError, match="names a config section"):
        parse_space({"optimizer": {"type": "categorical", "choices": [1]}}, tree)
    with pytest.raises(ValueError, match=r"needs low < high"):
        parse_space({"experts": {"type": "int", "low": 5, "high": 1}}, tree)
    with pytest.raises(ValueError, match=r"type must be one of"):
        parse_space({"experts": {"type": "uniform", "low": 1, "high": 5}}, tree)


@pytest.mark.parametrize(
    ("url", "match"),
    [
        ("optuna.db", "not a database URL"),
        ("postgres://u@localhost/optuna", r"write postgresql://"),
        ("oracle://u@localhost/optuna", "is not one of"),
    ],
)
def test_bad_storage_url_is_explained(url, match):
    with pytest.raises(ValueError, match=match):
        open_storage(url)


def test_unreachable_storage_is_explained():
    url = "postgresql+psycopg2://someone:secret@127.0.0.1:9/optuna"  # port 9: nobody listens
    with pytest.raises(ConnectionError, match="cannot open the Optuna storage") as err:
        open_storage(url)
    assert "secret" not in str(err.value)


def test_no_search_configured():
    with pytest.raises(ValueError, match="hparams_search=default"):
        run(compose_cfg())


# ------------------------------------------------------------- one fixed config per study
def test_resuming_a_study_under_another_budget_refuses(tmp_path, mlflow_uri):
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    common = _tune_overrides(
        tmp_path / "data", tmp_path, mlflow_uri, storage, "hparams_search.n_trials=0"
    )
    first = run(_cfg(*common))  # a 1-epoch study (no trial needed to record its config)
    fixed = first.user_attrs[FIXED_ATTR]
    assert fixed["trainer.max_epochs"] == "1" and fixed["hparams_search.metric"] == "val/loss"
    assert fixed["model.heads"] == "3"  # not searched: fixed
    searched_or_identity = ("model.hidden", "experts", "logger.tracking_uri", "paths.data_dir")
    assert not set(searched_or_identity) & set(fixed)
    n_runs = len(_runs(mlflow_uri, tmp_path.name))

    with pytest.raises(StudyConfigChangedError) as err:
        run(_cfg(*common, "trainer.max_epochs=60"))
    text = str(err.value)
    assert "trainer.max_epochs: 1 -> 60" in text and "'tiny'" in text
    assert "hparams_search.study_name=<new name>" in text
    assert "hparams_search.allow_config_change=true" in text
    assert len(_runs(mlflow_uri, tmp_path.name)) == n_runs  # refused before MLflow was touched

    # the same fixed config resumes, whatever the search settings, paths and tracking
    same = (
        "hparams_search.pruner=null",
        "hparams_search.sampler.seed=7",
        f"logger.artifact_location={tmp_path / 'elsewhere'}",
        f"paths.data_dir={tmp_path / 'data2'}",
        "hparams_search.params.model.hidden.choices=[8,32]",
    )
    again = run(_cfg(*common, *same))
    assert again._study_id == first._study_id
    assert again.user_attrs[FIXED_ATTR] == fixed

    allowed = run(
        _cfg(*common, "trainer.max_epochs=60", "hparams_search.allow_config_change=true")
    )
    assert allowed.user_attrs[FIXED_ATTR]["trainer.max_epochs"] == "60"
    (change,) = allowed.user_attrs[CHANGES_ATTR]
    assert change["changed"] == {"trainer.max_epochs": ["1", "60"]}
    assert run(_cfg(*common, "trainer.max_epochs=60"))._study_id == first._study_id


# ------------------------------------------------------------------- pruning and resuming
@pytest.mark.slow
def test_lightning_callback_prunes_and_rerun_continues_the_study(
    tiny_data_dir, tmp_path, mlflow_uri, caplog
):
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    scheme = ("logger.experiment_name=null", f"++logger.experiment_prefix={tmp_path.name}")
    common = _tune_overrides(tiny_data_dir, tmp_path, mlflow_uri, storage, *scheme)
    # every val/loss is above 0: the pruner prunes each trial at its first report
    prune_all = [
        "hparams_search.n_trials=2",
        "~hparams_search.pruner",  # replace the median pruner (a `=` would merge into it)
        "+hparams_search.pruner={_target_:optuna.pruners.ThresholdPruner,upper:0.0}",
    ]
    with caplog.at_level("INFO", logger="generalist_control.sweeps.study"):
        first = run(_cfg(*common, *prune_all))
    assert [t.state for t in first.trials] == [TrialState.PRUNED] * 2
    progress = [r.getMessage() for r in caplog.records if "of this run" in r.getMessage()]
    assert len(progress) == 2
    for k, line in enumerate(progress):  # a pruned trial's value: its last report
        value = first.trials[k].intermediate_values[0]
        assert line == (
            f"study 'tiny': trial {k} ({k + 1}/2 of this run) PRUNED value={value:.6g}; "
            "best so far: none yet"
        )
    for trial in first.trials:
        # reported and pruned by the pruning callback from inside trainer.fit, after epoch 0
        assert list(trial.intermediate_values) == [0]
        assert trial.user_attrs["pruned_at_epoch"] == 0
        assert not (Path(trial.user_attrs["trial_dir"]) / "models").exists()

    # the same command again continues the study: one more trial, never pruned this time
    second = run(_cfg(*common, "hparams_search.n_trials=1", "hparams_search.pruner=null"))
    assert second._study_id == first._study_id
    assert [t.number for t in second.trials] == [0, 1, 2]
    done = second.trials[2]
    assert done.state == TrialState.COMPLETE
    assert Path(done.user_attrs["trial_dir"], "models", "policy.ckpt").is_file()

    # the study and its trials are in the experiment of kind tune, nothing in train's
    mlflow.set_tracking_uri(mlflow_uri)
    assert mlflow.get_experiment_by_name(f"{tmp_path.name}/train") is None
    runs = {r.info.run_id: r for r in _runs(mlflow_uri, f"{tmp_path.name}/tune")}
    parent_id = second.user_attrs[PARENT_ATTR]
    parent = runs.pop(parent_id)
    assert parent.data.tags["gc.role"] == "study"
    assert parent.info.status == "FINISHED"
    assert parent.data.metrics["study/n_trials"] == 3
    assert parent.data.metrics["study/best_value"] == pytest.approx(done.value)
    assert len(runs) == 3  # one MLflow run per trial, all under the study's parent
    by_trial = {int(r.data.tags["optuna.trial"]): r for r in runs.values()}
    for number, mlrun in by_trial.items():
        assert mlrun.data.tags["mlflow.parentRunId"] == parent_id
        assert mlrun.data.tags["optuna.study"] == "tiny"
        assert mlrun.info.run_id == second.trials[number].user_attrs["mlflow_run_id"]
        values = second.trials[number].params  # the run is named after the trial's values
        assert mlrun.info.run_name == f"d{values['model.hidden']}-M{values['experts']}"
    assert [by_trial[n].info.status for n in (0, 1)] == ["KILLED", "KILLED"]
    assert by_trial[0].data.tags["optuna.state"] == "PRUNED"
    assert by_trial[2].info.status == "FINISHED"
    assert by_trial[2].data.metrics["best/val/loss"] == pytest.approx(done.value)
    assert {"closed_loop/mse/cstr", "closed_loop/mse_mean"} <= set(by_trial[2].data.metrics)


# ------------------------------------------------------------------------ several workers
@pytest.mark.slow
def test_two_workers_share_a_postgresql_study(tiny_data_dir, tmp_path, postgres_url):
    """Two `python tune.py` at once on one PostgreSQL study (and one MLflow database)."""
    mlflow_uri = create_database(postgres_url, "mlflow_two_workers")
    mlflow.set_tracking_uri(mlflow_uri)
    mlflow.MlflowClient().search_experiments()  # create MLflow's tables before the workers
    common = _tune_overrides(
        tiny_data_dir, tmp_path, mlflow_uri, postgres_url, "hparams_search.n_trials=2"
    )
    workers = [
        _worker([*common, f"hparams_search.worker={k}"], tmp_path / f"hydra{k}") for k in (0, 1)
    ]
    for proc in workers:
        out, _ = proc.communicate(timeout=300)
        assert proc.returncode == 0, out[-3000:]

    study = optuna.load_study(study_name="tiny", storage=postgres_url)
    trials = study.trials
    assert len(trials) == 4
    assert {t.state for t in trials} <= {TrialState.COMPLETE, TrialState.PRUNED}
    assert len({t.user_attrs["worker"] for t in trials}) == 2  # both workers ran trials
    assert len({tuple(sorted(t.params.items())) for t in trials}) == 4  # own seeds

    runs = _runs(mlflow_uri, tmp_path.name)
    parents = [r for r in runs if r.data.tags.get("gc.role") == "study"]
    assert [p.info.run_id for p in parents] == [study.user_attrs[PARENT_ATTR]]
    children = [r for r in runs if r not in parents]
    assert len(children) == 4
    assert {c.data.tags["mlflow.parentRunId"] for c in children} == {parents[0].info.run_id}


def _endless_worker(common: list[str], storage: str, hydra_dir: Path):
    """A worker whose one trial would train for hours, once its training has started."""
    endless = [
        "trainer.max_epochs=100000",
        "~callbacks.early_stopping",
        "hparams_search.n_trials=1",
    ]
    proc = _worker([*common, *endless], hydra_dir)
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.5)
        try:
            trials = optuna.load_study(study_name="tiny", storage=storage).trials
        except (KeyError, sqlalchemy.exc.SQLAlchemyError):  # no study (or tables) yet
            continue
        if trials and "mlflow_run_id" in trials[0].user_attrs:  # training has started
            return proc, trials[0]
    raise AssertionError(proc.communicate(timeout=30)[0][-3000:])


@pytest.mark.slow
def test_killed_workers_trial_fails_and_the_study_goes_on(tiny_data_dir, tmp_path, mlflow_uri):
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    heartbeat = ["hparams_search.heartbeat.interval=1", "hparams_search.heartbeat.grace_period=2"]
    common = _tune_overrides(tiny_data_dir, tmp_path, mlflow_uri, storage, *heartbeat)
    proc, trial = _endless_worker(common, storage, tmp_path / "hydra_killed")
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)
    assert optuna.load_study(study_name="tiny", storage=storage).trials[0].state == (
        TrialState.RUNNING
    )
    time.sleep(4)  # > grace period (SQLite's clock has whole seconds)

    # a short training this time: another fixed config than the killed one's, allowed
    again = ("hparams_search.n_trials=1", "hparams_search.allow_config_change=true")
    study = run(_cfg(*common, *again))
    states = [t.state for t in study.trials]
    assert states == [TrialState.FAIL, TrialState.COMPLETE]
    killed = mlflow.MlflowClient().get_run(trial.user_attrs["mlflow_run_id"])
    assert killed.info.status == "FAILED"
    assert killed.data.tags["optuna.state"] == "FAIL"


@pytest.mark.slow
def test_sigterm_fails_the_running_trial_and_ends_the_study_killed(
    tiny_data_dir, tmp_path, mlflow_uri
):
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    common = _tune_overrides(tiny_data_dir, tmp_path, mlflow_uri, storage)
    proc, trial = _endless_worker(common, storage, tmp_path / "hydra")
    proc.send_signal(signal.SIGTERM)
    out = proc.communicate(timeout=120)[0]
    assert proc.returncode == 128 + signal.SIGTERM, out[-3000:]
    assert "stopped by SIGTERM" in out
    study = optuna.load_study(study_name="tiny", storage=storage)
    assert [t.state for t in study.trials] == [TrialState.FAIL]  # not left RUNNING
    client = mlflow.MlflowClient(mlflow_uri)
    # the training stopped by the signal ends its run KILLED, as a plain training does
    assert client.get_run(trial.user_attrs["mlflow_run_id"]).info.status == "KILLED"
    assert client.get_run(study.user_attrs[PARENT_ATTR]).info.status == "KILLED"


def test_writes_to_the_shared_parent_run_retry_a_clash_between_workers():
    """Two workers ending at once clash on MLflow's read-then-insert of a tag: retried."""
    from mlflow.exceptions import MlflowException

    from generalist_control.tracking.mlflow_utils import retry_on_clash

    calls = []

    def flaky(key, value):
        calls.append((key, value))
        if len(calls) == 1:
            raise MlflowException('duplicate key value violates unique constraint "tag_pk"')
        return "ok"

    assert retry_on_clash(flaky, "study.best_params", "{}") == "ok"
    assert calls == [("study.best_params", "{}")] * 2

    def broken(*_):
        calls.append("broken")
        raise MlflowException("RESOURCE_DOES_NOT_EXIST: run not found")

    calls.clear()
    with pytest.raises(MlflowException, match="run not found"):
        retry_on_clash(broken, "x")
    assert calls == ["broken"]  # anything but a clash is raised at once


def test_fit_pruning_reports_during_the_fit_only():
    """The library's pruning callback, but not in the validate after the fit; no silent typo."""
    from types import SimpleNamespace

    import torch
    from lightning.pytorch.trainer.states import TrainerFn

    from generalist_control.sweeps.trial_callbacks import FitPruning

    study = optuna.create_study(pruner=optuna.pruners.ThresholdPruner(upper=0.5))
    trial = study.ask()
    callback = FitPruning(trial, "val/loss")
    trainer = SimpleNamespace(
        sanity_checking=False,
        state=SimpleNamespace(fn=TrainerFn.VALIDATING),
        callback_metrics={"val/loss": torch.tensor(1.0)},
    )
    module = SimpleNamespace(current_epoch=0)
    callback.on_validation_end(trainer, module)  # train()'s validate of the best checkpoint
    assert study.trials[0].intermediate_values == {}
    trainer.state.fn = TrainerFn.FITTING
    with pytest.raises(optuna.TrialPruned, match="epoch 0"):
        callback.on_validation_end(trainer, module)  # 1.0 > 0.5: pruned
    assert study.trials[0].intermediate_values == {0: 1.0}
    trainer.callback_metrics = {"val/los": torch.tensor(1.0)}
    with pytest.raises(KeyError, match=r"'val/loss' \(hparams_search\.monitor\); logged: val/los"):
        callback.on_validation_end(trainer, module)


# ------------------------------------------------------------------------------- dashboard
def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _get(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=10) as answer:
        return json.load(answer)


def test_the_dashboard_command_serves_the_studys_trials(tmp_path):
    """The README's ``optuna-dashboard <storage>``: the configured storage, served headless."""
    line = next(
        x for x in (REPO / "README.md").read_text().splitlines() if "optuna-dashboard" in x
    )
    command = line.split("#")[0].split()
    storage = compose_cfg(config="tune").hparams_search.storage
    assert command == ["optuna-dashboard", storage]  # the study tune.py writes by default
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    study = optuna.create_study(study_name="tiny", storage=url)
    for hidden in (8, 16, 32):
        study.enqueue_trial({"model.hidden": hidden})
    study.optimize(lambda t: t.suggest_categorical("model.hidden", [8, 16, 32]) / 8, n_trials=3)
    port = _free_port()
    env = {**os.environ, "HOME": str(tmp_path)}  # gunicorn's control socket goes there
    server = subprocess.Popen(
        [str(Path(sys.executable).parent / command[0]), url, "--host", "127.0.0.1",
         "--port", str(port)],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True,
    )  # fmt: skip
    base = f"http://127.0.0.1:{port}/api/studies"
    try:
        deadline = time.monotonic() + 60
        while True:
            assert server.poll() is None, server.communicate()[0][-3000:]
            try:
                summaries = _get(base)["study_summaries"]
                break
            except OSError:
                assert time.monotonic() < deadline, "the dashboard did not answer in 60 s"
                time.sleep(0.5)
        (summary,) = summaries
        assert summary["study_name"] == "tiny"
        trials = _get(f"{base}/{summary['study_id']}")["trials"]
        served = [
            (t["number"], t["state"], t["values"], [(p["name"], p["param_external_value"])
                                                    for p in t["params"]])
            for t in trials
        ]  # fmt: skip
        assert served == [
            (0, "Complete", [1.0], [("model.hidden", "8")]),
            (1, "Complete", [2.0], [("model.hidden", "16")]),
            (2, "Complete", [4.0], [("model.hidden", "32")]),
        ]
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.communicate(timeout=30)
    left = subprocess.run(
        ["ps", "-o", "pid=", "-s", str(server.pid)], capture_output=True, text=True
    )
    assert left.stdout.split() == []  # gunicorn's worker went with it


def test_two_parents_made_at_the_same_moment_become_one_when_a_worker_stops(tmp_path):
    """Each of two workers created a parent before the other's was visible: the newer's trial
    runs move under the older, and the newer is deleted."""
    from generalist_control.sweeps.study import _settled_parent
    from generalist_control.tracking.parents import create_parent_run

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    logger = {"tracking_uri": uri, "experiment_name": "merge/tune"}
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    study = optuna.create_study(study_name="s", storage=storage)
    tags = {"optuna.study": "s", "optuna.storage": storage}
    older = create_parent_run(logger, "study:s", "study", tags)
    time.sleep(0.01)  # a later start time
    newer = create_parent_run(logger, "study:s", "study", tags)
    client = mlflow.MlflowClient(uri)
    exp = client.get_run(newer).info.experiment_id
    trial_run = client.create_run(exp, tags={"mlflow.parentRunId": newer}).info.run_id

    assert _settled_parent(study, logger, storage, older) == older  # the older keeps its own
    assert client.get_run(newer).info.lifecycle_stage == "active"
    assert _settled_parent(study, logger, storage, newer) == older
    assert client.get_run(trial_run).data.tags["mlflow.parentRunId"] == older
    assert client.get_run(newer).info.lifecycle_stage == "deleted"
    assert study.user_attrs[PARENT_ATTR] == older
