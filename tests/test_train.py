"""The train stage end to end on tiny data: MLflow run, resume, missing data, determinism."""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import mlflow
import pytest
import torch
from hydra import compose, initialize_config_dir

from generalist_control.common.paths import conf_dir
from generalist_control.common.sections import as_dict
from generalist_control.data.demos import MissingDataError, content_hash, load_demos
from generalist_control.deploy.policy_source import resolve
from generalist_control.model.policy import FlatPolicy, load_policy, policy_sha256
from generalist_control.tracking.mlflow_utils import find_training_run
from helpers import run_command, tiny_train_overrides, train

REPO = Path(__file__).resolve().parents[1]


def _overrides(data_dir: Path, out: Path, uri: str, *extra: str) -> list[str]:
    """Shrink the real config: tiny data, CPU, one epoch, outputs under ``out``."""
    return tiny_train_overrides(data_dir, out, uri, *extra)


def _cfg(overrides: list[str]):
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return compose("config", overrides=overrides)


@pytest.mark.slow
def test_exact_command_logs_an_mlflow_run(tiny_data_dir, tmp_path, mlflow_uri):
    """`python train.py model.hidden=64 experts=5` (plus tiny-data overrides), one epoch."""
    overrides = _overrides(
        tiny_data_dir, tmp_path, mlflow_uri, f"hydra.run.dir={tmp_path / 'hydra'}"
    )
    cmd = [sys.executable, "train.py", "model.hidden=64", "experts=5", *overrides]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    proc = run_command(cmd, cwd=REPO, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]

    mlflow.set_tracking_uri(mlflow_uri)
    (run,) = mlflow.search_runs(experiment_names=[tmp_path.name], output_format="list")
    assert run.info.status == "FINISHED"
    params = run.data.params
    assert params["model.hidden"] == "64"
    assert params["experts"] == "5"
    assert int(params["n_parameters"]) > 0
    # what shaped the training, not evaluation/report/paths/logger/Hydra settings
    assert 20 < len(params) < 60, sorted(params)  # the parts and their settings only
    assert not [k for k in params if k.startswith(("evaluation.", "report.", "paths."))]
    assert not [k for k in params if k.startswith(("logger.", "hydra.", "_"))]
    assert {"seed", "loader.batch_size", "trainer.max_epochs", "dagger.rounds"} <= set(params)
    manifest = json.loads((tiny_data_dir / "manifest.json").read_text())
    assert run.data.tags["data.content_hash"] == manifest["content_hash"]
    assert params["data.content_hash"] == manifest["content_hash"]
    # the dataset input: its digest is the content hash computed afresh from the data
    fresh = content_hash(*load_demos(tiny_data_dir, verify=False)[:1], manifest["config"])
    (data_input,) = run.inputs.dataset_inputs
    assert data_input.dataset.digest == fresh.removeprefix("sha256:")[:36]
    input_tags = {t.key: t.value for t in data_input.tags}
    assert input_tags == {"mlflow.data.context": "training", "content_hash": fresh}
    assert str(tiny_data_dir.resolve()) in data_input.dataset.source
    metrics = run.data.metrics
    assert {"train/loss", "val/loss", "val/mse/cstr", "val/mse/hydraulic_actuator"} <= set(metrics)
    artifacts = {a.path for a in mlflow.MlflowClient().list_artifacts(run.info.run_id)}
    assert {"checkpoints", "config", "data", "policy"} <= artifacts
    (model,) = mlflow.search_logged_models(
        experiment_ids=[run.info.experiment_id], output_format="list"
    )
    assert model.source_run_id == run.info.run_id
    assert mlflow.models.get_model_info(model.model_uri).signature is not None

    policy, meta = load_policy(tmp_path / "models" / "policy.ckpt")
    assert policy.config["hidden"] == 64 and policy.net.n_experts == 5
    assert meta["content_hash"] == manifest["content_hash"]
    # the file holds no run id (its bytes reproduce); its run is found by its hash
    assert "mlflow_run_id" not in meta
    sha = policy_sha256(tmp_path / "models" / "policy.ckpt")
    assert run.data.tags["policy.sha256"] == sha
    assert find_training_run(sha) == run.info.run_id
    saved = json.loads((tmp_path / "models" / "metrics.json").read_text())
    assert saved["val/loss"] == pytest.approx(metrics["best/val/loss"], rel=1e-6)
    mse_mean = metrics["closed_loop/mse_mean"]
    assert saved["closed_loop/log10_mse_mean"] == pytest.approx(math.log10(mse_mean), abs=1e-6)
    _check_registered(run, policy, meta["tags"], proc.stdout + proc.stderr, mlflow_uri)


def _check_registered(run, policy, tags: dict, log: str, uri: str) -> None:
    """The run's registered version: tagged with the run, loads, controls as the policy."""
    client = mlflow.MlflowClient()
    (version,) = [
        v
        for v in client.search_model_versions("name = 'generalist-control-policy'")
        if v.run_id == run.info.run_id
    ]
    assert version.tags["run_id"] == run.info.run_id
    assert version.tags["data.content_hash"] == run.data.tags["data.content_hash"]
    uri_v = f"models:/generalist-control-policy/{version.version}"
    registered, _ = load_policy(resolve(uri_v))
    flat = FlatPolicy(policy).eval()
    info = mlflow.models.get_model_info(uri_v)
    assert info.signature is not None and info.saved_input_example_info is not None
    x = torch.randn(16, int(info.signature.inputs.to_dict()[0]["tensor-spec"]["shape"][1]))
    x[:, -1] = torch.tensor(sorted(tags.values()), dtype=x.dtype).repeat(8)  # the two plants
    with torch.no_grad():
        expected, got = flat(x), FlatPolicy(registered).eval()(x)
    assert torch.equal(expected, got)
    pyfunc = mlflow.pyfunc.load_model(uri_v)
    assert torch.allclose(torch.as_tensor(pyfunc.predict(x.numpy())), expected, atol=1e-6)
    # the end message names the policy, the run, its experiment, the version and the UI
    line = next(ln for ln in log.splitlines() if "policy written to" in ln)
    for part in (run.info.run_id, "experiment '", f"version {version.version}", "mlflow ui"):
        assert part in line, line
    assert uri in line


#: The short trainings of the resume and determinism tests: no MLflow model, 128 a batch.
SHORT = ("logger.log_model=false", "loader.batch_size=128")


@pytest.fixture(scope="module")
def first(tiny_data_dir, tmp_path_factory, mlflow_uri) -> tuple[Path, dict, dict]:
    """One :data:`SHORT` training under ``<tmp>/a``, the one the resume test resumes and the
    determinism test repeats: its folder, metrics and objects (neither test changes them)."""
    out = tmp_path_factory.mktemp("first") / "a"
    metrics, objects = train(_cfg(_overrides(tiny_data_dir, out, mlflow_uri, *SHORT)))
    return out, metrics, objects


@pytest.mark.slow
def test_resume_continues_from_the_checkpoint(first, tiny_data_dir, tmp_path, mlflow_uri):
    a, _, objs1 = first
    trainer1 = objs1["trainer"]
    last = a / "run" / "checkpoints" / "last.ckpt"
    assert last.is_file() and trainer1.current_epoch == 1
    blob = torch.load(last, weights_only=True)  # Lightning checkpoints load without pickle too
    assert blob["epoch"] == 0

    overrides = _overrides(
        tiny_data_dir,
        tmp_path / "b",
        mlflow_uri,
        *SHORT,
        f"ckpt_path={last}",
        "trainer.max_epochs=2",
    )
    second, objs2 = train(_cfg(overrides))
    trainer2 = objs2["trainer"]
    assert trainer2.current_epoch == 2
    assert trainer2.global_step == 2 * trainer1.global_step
    # the resumed training logs into the same MLflow run, one more epoch
    assert objs2["run_id"] == objs1["run_id"]
    history = mlflow.MlflowClient().get_metric_history(objs2["run_id"], "val/loss")
    assert sorted(m.step for m in history) == [0, 1]


def test_missing_data_error_gives_the_command(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = _cfg(_overrides(tmp_path / "nowhere", tmp_path, uri))
    with pytest.raises(MissingDataError, match=r"python -m generalist_control\.generate"):
        train(cfg)
    assert not (tmp_path / "mlflow.db").exists()  # failed before anything was logged


@pytest.mark.slow
def test_training_is_deterministic(first, tiny_data_dir, tmp_path, mlflow_uri):
    _, m1, o1 = first  # the same config, trained earlier in this process
    m2, o2 = train(_cfg(_overrides(tiny_data_dir, tmp_path / "b", mlflow_uri, *SHORT)))
    assert m2["val/loss"] == pytest.approx(m1["val/loss"], rel=1e-6)
    assert m2["train/loss"] == pytest.approx(m1["train/loss"], rel=1e-6)
    # same weights, same bytes: the pipeline's policy.ckpt leaves dvc.lock as it was
    assert o1["policy_path"].read_bytes() == o2["policy_path"].read_bytes()
    assert o1["run_id"] != o2["run_id"]


def test_experiment_paper_is_the_baseline():
    cfg = _cfg(["experiment=paper"])
    assert cfg.model.hidden == 32 and cfg.experts == 3 and cfg.model.heads == 3
    assert cfg.optimizer.lr == pytest.approx(1e-3)
    assert cfg.optimizer.weight_decay == pytest.approx(1e-5)
    assert cfg.trainer.gradient_clip_val == 1.0
    assert cfg.data.history == 8 and cfg.data.horizon == 3
    assert cfg.systems.name == "all"
    # the paper's policy sees no error integral and has no linear path
    assert not cfg.model.channels and "skip" not in cfg.model
    assert not cfg.model.window_scale and cfg.dagger is None


def test_default_recipe_config_composes_the_learned_generalist():
    from generalist_control.model.policy import Policy
    from generalist_control.training.settings import read_training

    cfg = _cfg([])
    policy = Policy(read_training(as_dict(cfg)).model)
    # the learned generalist: the integral channel, window scaling and the shared skip path
    assert policy.channels == ("integral",) and policy.net.window_scale
    assert policy.net.skip is not None
    assert cfg.dagger.sampler.families == 1 and set(cfg.data.families) >= {"staircase", "hold"}


def test_conf_model_is_instantiated_alone_with_hydra():
    """`hydra.utils.instantiate(cfg.model)` builds the network; `experts=5` reaches it."""
    from hydra.utils import instantiate

    from generalist_control.model.network import GeneralistNetwork

    net = instantiate(_cfg(["experts=5", "data.history=6"]).model)
    assert isinstance(net, GeneralistNetwork)
    assert net.n_experts == 5 and len(net.experts) == 5 and net.history == 6
    assert net.horizon == 3 and net.skip is not None and net.n_tags == 25
