"""MLflow for the evaluate stage in a worker process: it logs, and its errors reach us."""

from __future__ import annotations

import mlflow
import numpy as np
import pytest

from generalist_control.common.configs import as_dict
from generalist_control.evaluation import tracker
from generalist_control.evaluation.tracker import MlflowWorker, MlflowWorkerError
from helpers import compose_cfg


def _logger(uri: str, name: str) -> dict:
    return as_dict(compose_cfg(f"logger.tracking_uri={uri}", f"logger.experiment_name={name}")
                   .logger)  # fmt: skip


def test_the_worker_logs_the_figures_and_the_folder(tmp_path, mlflow_uri):
    out = tmp_path / "eval"
    out.mkdir()
    (out / "summary.json").write_text("{}\n")
    summary = {"ratios": {"step": {"worst_ISE_ratio": np.float64(1.5), "worst": float("nan")}},
               "diverged": {"GC": {"step": np.int64(1)}}}  # fmt: skip
    with MlflowWorker(_logger(mlflow_uri, tmp_path.name), "ev") as worker:
        assert worker.ready() == mlflow_uri
        run_id = worker.log(None, summary, out)
    # it ended cleanly, after answering everything it was sent
    assert worker._proc.returncode == 0
    mlflow.set_tracking_uri(mlflow_uri)
    run = mlflow.get_run(run_id)
    assert run.data.metrics == {"ev/step/worst_ISE_ratio": 1.5, "ev/diverged/GC": 1.0}
    names = [a.path for a in mlflow.MlflowClient().list_artifacts(run_id, "ev")]
    assert names == ["ev/summary.json"]


def test_a_store_that_cannot_be_opened_is_an_error_of_the_evaluation(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    uri = f"sqlite:///{tmp_path / 'file' / 'mlflow.db'}"
    with MlflowWorker(_logger(uri, "x"), "eval") as worker, pytest.raises(MlflowWorkerError):
        worker.ready()


def test_an_early_worker_is_taken_over_and_one_never_configured_opens_no_store(
    tmp_path, mlflow_uri, monkeypatch
):
    monkeypatch.setattr(tracker, "_early", None)
    tracker.start_early()
    early = tracker._early
    with MlflowWorker(_logger(mlflow_uri, tmp_path.name), "ev") as worker:
        assert worker._proc is early and worker.ready() == mlflow_uri
    assert tracker._early is None and early.returncode == 0
    # a worker started early that is never sent its config ends when its stdin closes
    monkeypatch.chdir(tmp_path)
    tracker.start_early()
    lone, tracker._early = tracker._early, None
    assert lone is not None and lone.stdin is not None
    lone.stdin.close()
    assert lone.wait(timeout=120) == 0
    if lone.stdout is not None:
        lone.stdout.close()
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "mlruns").exists()
