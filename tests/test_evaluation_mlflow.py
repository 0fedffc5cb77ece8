"""An evaluation in MLflow and in its folder: a run of its own, never the training run reopened;
a store that does not answer refused before anything is written; one evaluation per folder.

The policy is the LQI law itself (``helpers.lqi_law_policy``): no training needed. Its
"training run" is made here, with a logged model as MLflow 3's training logs one.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import mlflow
import pytest
from mlflow.entities import LoggedModelOutput

from generalist_control.common.atomic import FolderBusy, folder_lock
from generalist_control.evaluate import run as evaluate_run
from generalist_control.model.policy import policy_sha256, save_policy
from generalist_control.simulation.lqi import design_lqi
from generalist_control.tracking import mlflow_utils
from generalist_control.tracking.mlflow_utils import KIND_TAG, POLICY_HASH_TAG
from helpers import compose_cfg, lqi_law_policy

#: One short scenario on one plant: seconds per evaluation.
QUICK = (
    "systems.include=[cstr]",
    "~evaluation.scenarios",
    "+evaluation.scenarios={step: {kind: step, amplitude: 1.0, duration: 3.0}}",
    "evaluation.setpoint=null",
    "evaluation.plots=false",
    "evaluation.backend=torch",
)


def _training_run(uri: str, experiment: str, policy: Path) -> str:
    """A finished training run that wrote ``policy``, with a logged model, as ``python
    train.py`` leaves one (the policy file names no run: its hash is the run's tag)."""
    logger = {"tracking_uri": uri, "experiment_name": experiment}
    exp_id = mlflow_utils.experiment_id(logger, kind="train")
    client = mlflow.MlflowClient(uri)
    run_id = client.create_run(exp_id, run_name="d16-M2").info.run_id
    model = client.create_logged_model(exp_id, name="policy", source_run_id=run_id)
    client.log_outputs(run_id, [LoggedModelOutput(model.model_id, step=0)])
    client.set_tag(run_id, POLICY_HASH_TAG, policy_sha256(policy))
    client.set_terminated(run_id, "FINISHED")
    return run_id


def _policy(path: Path, **meta: str) -> Path:
    """The LQI-law policy; ``meta`` makes its file's bytes (and hash) its own."""
    pol, facts = lqi_law_policy(["cstr"], design_lqi)
    return save_policy(path, pol, {**facts, **meta})


def _evaluate(policy: Path, reports: Path, *overrides: str) -> dict:
    return evaluate_run(compose_cfg(f"policy={policy}", f"paths.reports_dir={reports}",
                                    *QUICK, *overrides))  # fmt: skip


def test_evaluations_log_runs_of_their_own_and_leave_the_training_run_as_it_was(
    tmp_path, mlflow_uri
):
    policy = _policy(tmp_path / "policy.ckpt", data_dir=tmp_path.name)
    training_id = _training_run(mlflow_uri, tmp_path.name, policy)
    client = mlflow.MlflowClient(mlflow_uri)
    before = client.get_run(training_id).info
    logger = (f"logger.tracking_uri={mlflow_uri}", f"logger.experiment_name={tmp_path.name}")
    for _ in range(2):
        _evaluate(policy, tmp_path / "reports", *logger)
    after = client.get_run(training_id).info
    assert (after.start_time, after.end_time, after.status) == (
        before.start_time, before.end_time, "FINISHED"
    )  # fmt: skip
    runs = client.search_runs([before.experiment_id], f"tags.`gc.source_run_id` = '{training_id}'")
    assert len(runs) == 2
    for run in runs:
        assert run.data.tags["mlflow.parentRunId"] == training_id
        assert run.info.status == "FINISHED" and run.info.start_time >= before.end_time
        assert run.info.run_name == "eval d16-M2" and run.data.metrics["eval/bar_checked"] > 0
    # the figures are linked to the model the training logged (MLflow 3's model page)
    (model_id,) = [o.model_id for o in client.get_run(training_id).outputs.model_outputs]
    linked = {m.run_id for m in client.get_logged_model(model_id).metrics}
    assert linked == {r.info.run_id for r in runs}
    # the last run's artifacts are the files it published, and its folder names it
    newest = max(runs, key=lambda r: r.info.start_time)
    record = json.loads((tmp_path / "reports" / "provenance.json").read_text())
    assert record["mlflow"]["run_id"] == newest.info.run_id
    logged = mlflow.artifacts.download_artifacts(
        run_id=newest.info.run_id, artifact_path="eval/summary.json", dst_path=str(tmp_path / "a")
    )
    assert Path(logged).read_bytes() == (tmp_path / "reports" / "summary.json").read_bytes()
    assert client.get_experiment(before.experiment_id).tags[KIND_TAG[0]] == KIND_TAG[1]


def test_a_policy_whose_training_run_is_elsewhere_is_evaluated_in_the_evaluate_experiment(
    tmp_path, mlflow_uri
):
    policy = _policy(tmp_path / "policy.ckpt", data_dir="elsewhere")  # no run here wrote it
    _evaluate(policy, tmp_path / "reports", f"logger.tracking_uri={mlflow_uri}",
              f"logger.experiment_prefix={tmp_path.name}")  # fmt: skip
    experiment = mlflow.MlflowClient(mlflow_uri).get_experiment_by_name(
        f"{tmp_path.name}/evaluate"
    )
    assert experiment is not None and experiment.tags[KIND_TAG[0]] == KIND_TAG[1]
    (run,) = mlflow.MlflowClient(mlflow_uri).search_runs([experiment.experiment_id])
    assert "mlflow.parentRunId" not in run.data.tags
    assert run.data.tags["gc.source_run_id"] == ""


def test_an_unreachable_tracking_server_is_refused_before_any_output_changes(
    tmp_path, mlflow_uri, monkeypatch
):
    policy = _policy(tmp_path / "policy.ckpt")
    reports = tmp_path / "reports"
    _evaluate(policy, reports, f"logger.tracking_uri={mlflow_uri}")
    before = {p.name: p.read_bytes() for p in reports.iterdir()}
    monkeypatch.delenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", raising=False)  # MLflow's default
    start = time.monotonic()
    with pytest.raises(ConnectionError, match=r"http://127\.0\.0\.1:9 \(logger\.tracking_uri\)"):
        _evaluate(policy, reports, "logger.tracking_uri=http://127.0.0.1:9")
    assert time.monotonic() - start < 60  # one try, not minutes of back-off
    assert {p.name: p.read_bytes() for p in reports.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["policy.ckpt", "reports"]  # no lock
    with pytest.raises(ConnectionError):  # into a new folder: none made, none left
        _evaluate(policy, tmp_path / "new" / "eval", "logger.tracking_uri=http://127.0.0.1:9")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["policy.ckpt", "reports"]


#: Holds the lock of a folder until its stdin closes.
_HOLDER = """
import sys
from generalist_control.common.atomic import FolderBusy, folder_lock
with folder_lock(sys.argv[1], "evaluation"):
    print("held", flush=True)
    sys.stdin.read()
"""


def test_a_second_evaluation_of_a_folder_waits_for_the_first(tmp_path, caplog):
    out = tmp_path / "reports"
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(out)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert holder.stdout is not None and holder.stdout.readline() == "held\n"
    released = []

    def release() -> None:
        time.sleep(1.0)
        released.append(time.monotonic())
        assert holder.stdin is not None
        holder.stdin.close()

    threading.Thread(target=release).start()
    with caplog.at_level(logging.WARNING), folder_lock(out, "evaluation"):
        got = time.monotonic()
    holder.wait(timeout=60)
    holder.stdout.close()
    assert released and got >= released[0]
    assert f"{out} is being written by evaluation pid {holder.pid}" in caplog.text


def test_a_waiter_whose_lock_file_was_removed_takes_the_new_one(tmp_path):
    """The holder removes the lock file as it ends: its waiter must lock the file now at the
    place, so that a third command is still kept out."""
    out, first, holding, done = tmp_path / "reports", ExitStack(), threading.Event(), []
    first.enter_context(folder_lock(out, "first"))

    def second() -> None:
        with folder_lock(out, "second"):
            holding.set()
            time.sleep(1.0)
        done.append(True)

    waiter = threading.Thread(target=second)
    waiter.start()
    time.sleep(0.5)  # the second waits on the first's file
    first.close()
    assert holding.wait(timeout=30)
    with pytest.raises(FolderBusy, match="is being written by second pid"):
        with folder_lock(out, "third", wait=False):
            pass
    waiter.join(timeout=30)
    assert done and not list(tmp_path.iterdir())


#: Loads a policy by its MLflow URI, then exits.
_LOAD = """
import sys, mlflow
from generalist_control.deploy.policy_source import resolve
from generalist_control.model.policy import load_policy
mlflow.set_tracking_uri(sys.argv[1])
load_policy(resolve(sys.argv[2]))
"""


def test_a_policy_fetched_from_mlflow_leaves_no_temporary_folder(tmp_path, mlflow_uri):
    policy = _policy(tmp_path / "policy.ckpt")
    mlflow.set_tracking_uri(mlflow_uri)
    mlflow.set_experiment(tmp_path.name)
    with mlflow.start_run() as run:
        mlflow.log_artifact(str(policy), artifact_path="policy")
    (tmp_path / "temp").mkdir()
    env = {**os.environ, "TMPDIR": str(tmp_path / "temp")}
    done = subprocess.run([sys.executable, "-c", _LOAD, mlflow_uri, f"runs:/{run.info.run_id}"],
                          env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert not list((tmp_path / "temp").iterdir())
