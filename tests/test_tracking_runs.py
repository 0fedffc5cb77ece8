"""A training's MLflow run without training: params, experiment routing, metrics.json, messages.

Issue 12, items 2, 3, 4 (``dvc metrics show``) and 5 (the end message). The trainings
themselves are in tests/test_train.py (registered model, dataset input, end message).
"""

from __future__ import annotations

import math
import os
import socket
import subprocess

import mlflow
import pytest
import torch
from omegaconf import OmegaConf

from generalist_control.common.secrets import redact
from generalist_control.tracking import mlflow_utils, training_run
from generalist_control.tracking.parents import parent_run
from generalist_control.training.outputs import DVC_METRICS, dvc_metrics, end_message
from helpers import compose_cfg


def _resolved(*overrides: str) -> dict:
    cfg = compose_cfg(*overrides)
    return OmegaConf.to_container(cfg, resolve=True), list(cfg.logger.params)


def test_training_params_are_what_shaped_the_training():
    resolved, keys = _resolved("model.hidden=64", "experts=5")
    params = training_run.training_params(resolved, keys)
    # + data.content_hash and n_parameters: fewer than 60 (the parts the run was built from
    # and their settings, nothing that is off)
    assert len(params) + 2 < 60, sorted(params)
    assert params["model.hidden"] == "64" and params["experts"] == "5"
    assert params["optimizer.lr"] == "0.001" and params["seed"] == "42"
    # a part is logged as its class, its settings under it; nulls (parts not chosen) never
    assert params["model"] == "GeneralistNetwork" and params["model.plant"] == "TagEmbedding"
    assert params["model.skip"] == "LinearSkip" and params["optimizer"] == "AdamW"
    assert params["dagger.sampler.rollouts"] == "8"
    assert not [
        k for k in params if k.startswith(("model.law_history", "dagger.sampler.actuator"))
    ]
    assert [k for k, v in params.items() if v == "None"] == ["systems.include"]  # a chosen key
    assert params["trainer.max_epochs"] == "30" and params["dagger.rounds"] == "5"
    assert params["monitor"] == "val/closed_loop"
    # independent reference: every param is a config key of a chosen group, none of the others
    banned = ("evaluation.", "report.", "paths.", "logger.", "hydra.", "callbacks.model_")
    assert not [k for k in params if k.startswith(banned) or k.endswith("._partial_")]
    assert all(k == g or k.startswith(g + ".") for k in params for g in [_group(k, keys)])
    # a section that is off is logged as None alone
    off, _ = _resolved("dagger=null")
    params = training_run.training_params(off, keys)
    assert [k for k in params if k.startswith("dagger")] == ["dagger"]
    assert params["dagger"] == "None"
    # the tag-free recipe: its parts, and still fewer than 60
    tag_free, _ = _resolved("experiment=tag_free")
    params = training_run.training_params(tag_free, keys)
    assert len(params) + 2 < 60, sorted(params)
    assert params["model.plant"] == "InferredPlant" and params["model.skip"] == "ContextSkip"
    assert params["model.plant.identifier.models"] == "TransitionModels"
    assert params["dagger.sampler.actuator.lag"] == "1.0"


def _group(key: str, groups: list[str]) -> str:
    (group,) = [g for g in groups if key == g or key.startswith(g + ".")]
    return group


def test_metrics_json_reads_well_at_dvc_precision():
    metrics = {
        "val/loss": 0.0035093280021101236,
        "train/loss": 0.04353262856602669,
        "val/closed_loop": 1.420085482095601e-06,
        "closed_loop/mse_mean": 3.2e-12,
        "closed_loop/mse/cstr": 4.0e-06,
        "closed_loop/diverged": 0.0,
        "epochs": 30,
        "n_parameters": 56484,
        "global_step": 35594,
    }
    out = dvc_metrics(metrics)
    assert set(out) == set(DVC_METRICS)  # a few headline numbers, nothing per plant
    assert out["closed_loop/log10_mse_mean"] == pytest.approx(-11.49485, abs=1e-5)
    assert out["val/log10_closed_loop"] == pytest.approx(math.log10(1.420085482095601e-06))
    assert out["val/loss"] == pytest.approx(metrics["val/loss"], rel=1e-6)
    assert out["epochs"] == 30 and isinstance(out["epochs"], int)
    # what `dvc metrics show` prints (5 decimals) still tells the closed-loop errors apart
    assert round(out["closed_loop/log10_mse_mean"], 5) != 0.0
    assert round(metrics["closed_loop/mse_mean"], 5) == 0.0  # the raw value would not
    assert dvc_metrics({"closed_loop/mse_mean": math.inf}) == {
        "closed_loop/log10_mse_mean": math.inf
    }


def test_a_training_run_goes_to_the_train_experiment_or_its_parents(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    logger = {"tracking_uri": uri, "experiment_prefix": "p", "run_name": "d32-M3"}
    mlf = training_run.training_logger(logger)
    client = mlflow.MlflowClient(uri)
    run = client.get_run(mlf.run_id)
    assert client.get_experiment(run.info.experiment_id).name == "p/train"
    assert run.data.tags["mlflow.runName"] == "d32-M3" and run.data.tags["gc.pid"]
    assert "mlflow.parentRunId" not in run.data.tags

    sweep_exp = mlflow_utils.experiment_id(logger, kind="sweep")
    parent = client.create_run(sweep_exp, run_name="sweep:x").info.run_id
    with parent_run(parent, "sweep:x"):
        child = client.get_run(training_run.training_logger(logger).run_id)
    assert child.info.experiment_id == sweep_exp
    assert child.data.tags["mlflow.parentRunId"] == parent
    assert child.data.tags["sweep"] == "sweep:x"

    # resume: the same run; an unknown run id starts a new one
    again = training_run.training_logger(logger, resume_run_id=mlf.run_id)
    assert again.run_id == mlf.run_id
    assert training_run.training_logger(logger, resume_run_id="f" * 32).run_id != mlf.run_id
    explicit = {**logger, "experiment_name": "mine"}
    mine = client.get_run(training_run.training_logger(explicit).run_id)
    assert client.get_experiment(mine.info.experiment_id).name == "mine"


def test_the_run_id_is_recovered_from_a_checkpoint(tmp_path):
    recorder = training_run.RunRecorder("abc123")
    path = tmp_path / "last.ckpt"
    torch.save({"callbacks": {type(recorder).__qualname__: recorder.state_dict()}}, path)
    assert training_run.run_id_from_checkpoint(path) == "abc123"
    torch.save({"callbacks": {"MLflowEpochLogger": {"run_id": "old"}}}, path)  # before
    assert training_run.run_id_from_checkpoint(path) == "old"
    torch.save({"callbacks": {}}, path)
    assert training_run.run_id_from_checkpoint(path) is None


def test_end_message_names_policy_run_version_and_ui(tmp_path):
    uri = "http://gc:hunter2@mlflow.example:5000"
    line = end_message(tmp_path / "policy.ckpt", "r1", "gc/train", uri, "7", "policy")
    assert f"policy written to {tmp_path / 'policy.ckpt'}" in line
    assert "MLflow run r1 in experiment 'gc/train'" in line
    assert "registered model policy version 7" in line
    assert "hunter2" not in line and f"open {redact(uri)}" in line
    local = end_message(tmp_path / "p.ckpt", "r1", "gc/train", "sqlite:///mlflow.db", None, "x")
    assert "not registered" in local
    assert "mlflow ui --backend-store-uri sqlite:///mlflow.db" in local


def _numpy_dataset(digest: str):
    import numpy as np
    from mlflow.data.numpy_dataset import from_numpy

    return from_numpy(np.zeros((3, 2)), source="/data/demos", name="demos", digest=digest)


def test_a_dataset_logged_by_another_run_at_the_same_time_is_linked(tmp_path, monkeypatch):
    """Two runs insert one dataset together: the second insert breaks the unique key, then links.

    The race of two study workers is reproduced on a real store: just before this run's
    transaction writes its rows (after its lookup missed the dataset), another run logs the
    same dataset and commits; the transaction then fails on ``datasets``' unique key.
    """
    from sqlalchemy.orm import Session

    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = mlflow.create_experiment("race", artifact_location=(tmp_path / "art").as_uri())
    client = mlflow.MlflowClient()
    other = client.create_run(exp).info.run_id
    real_add_all, racing = Session.add_all, []

    def add_all(session, objs):
        objs = list(objs)
        if racing and any(type(o).__name__ == "SqlDataset" for o in objs):
            dataset = racing.pop()  # the other worker commits the same dataset first
            with mlflow.start_run(run_id=other, nested=True):
                mlflow.log_input(dataset, context="training")
        return real_add_all(session, objs)

    monkeypatch.setattr(Session, "add_all", add_all)
    with mlflow.start_run(experiment_id=exp) as run:
        racing.append(_numpy_dataset("d" * 36))
        with pytest.raises(mlflow.exceptions.MlflowException, match="UNIQUE constraint"):
            mlflow.log_input(racing[0], context="training")  # MLflow alone fails
        assert not racing
        dataset = _numpy_dataset("f" * 36)
        racing.append(dataset)
        mlflow_utils.retry_on_clash(
            mlflow.log_input, dataset, context="training", tags={"content_hash": "x"}
        )
    assert not racing  # the race happened on the shared path too, and it recovered
    (linked,) = client.get_run(run.info.run_id).inputs.dataset_inputs
    assert linked.dataset.digest == "f" * 36
    assert {t.key: t.value for t in linked.tags}["content_hash"] == "x"
    other_inputs = client.get_run(other).inputs.dataset_inputs
    assert sorted(i.dataset.digest for i in other_inputs) == ["d" * 36, "f" * 36]
    client.set_terminated(other)


def test_other_mlflow_errors_of_log_input_are_raised_at_once(monkeypatch):
    calls = []

    def fail(*args, **kwargs):
        calls.append(1)
        raise mlflow.exceptions.MlflowException("RESOURCE_DOES_NOT_EXIST: run not found")

    monkeypatch.setattr(mlflow, "log_input", fail)
    with pytest.raises(mlflow.exceptions.MlflowException, match="run not found"):
        mlflow_utils.retry_on_clash(
            mlflow.log_input, _numpy_dataset("e" * 36), context="training", tags={}
        )
    assert calls == [1]


def test_a_run_reopened_since_the_search_is_not_set_killed(tmp_path, monkeypatch):
    """end_stale_runs judges each run again under the store's lock: a run an evaluation
    reopened (its live process's tags) after the search saw the dead training's stays."""
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    client = mlflow.MlflowClient()
    exp = client.create_experiment("stale")
    run_id = client.create_run(exp).info.run_id
    gone = subprocess.Popen(["true"])
    gone.wait()  # a process that has ended: its pid is the training's that was killed
    client.set_tag(run_id, mlflow_utils.HOST_TAG, socket.gethostname())
    client.set_tag(run_id, mlflow_utils.PID_TAG, str(gone.pid))
    seen = client.search_runs([exp])  # what a concurrent search saw: the dead pid
    client.set_tag(run_id, mlflow_utils.PID_TAG, str(os.getpid()))  # reopened, alive
    client.set_tag(run_id, mlflow_utils.START_TAG, "")
    monkeypatch.setattr(mlflow.MlflowClient, "search_runs", lambda self, *a, **k: seen)
    assert mlflow_utils.end_stale_runs(exp) == []
    assert client.get_run(run_id).info.status == "RUNNING"
    client.set_tag(run_id, mlflow_utils.PID_TAG, str(gone.pid))  # now it is gone
    assert mlflow_utils.end_stale_runs(exp) == [run_id]
    assert client.get_run(run_id).info.status == "KILLED"


def test_a_new_run_ends_the_runs_of_processes_that_are_gone(tmp_path):
    logger = {"tracking_uri": f"sqlite:///{tmp_path / 'mlflow.db'}", "experiment_name": "gone"}
    with mlflow_utils.mlflow_run(logger) as run:
        model_run = run.info.run_id
    client = mlflow.MlflowClient()
    exp = client.get_run(model_run).info.experiment_id
    dead = client.create_run(exp).info.run_id
    gone = subprocess.Popen(["true"])
    gone.wait()
    client.set_tag(dead, mlflow_utils.HOST_TAG, socket.gethostname())
    client.set_tag(dead, mlflow_utils.PID_TAG, str(gone.pid))
    assert client.get_run(dead).info.status == "RUNNING"
    with mlflow_utils.mlflow_run(logger):
        pass
    assert client.get_run(dead).info.status == "KILLED"
