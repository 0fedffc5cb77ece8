"""The whole DVC pipeline on a tiny configuration, in a throw-away git repository.

generate -> train -> evaluate run once, then a second ``dvc repro`` skips every stage;
then the ablation pipeline, the paper's recipe on two points. The tiny configuration is set
the way a user sets parameters: ``dvc exp run -S <conf file>:<key>=<value>`` on the Hydra
config files (docs/pipeline.md), which also runs the pipeline, exactly as ``dvc repro``
does, and records the experiment.
"""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from generalist_control.model.policy import load_policy
from generalist_control.reports.figures import FIGURES, figure_key, read_tables

ROOT = Path(__file__).resolve().parents[1]
DVC = [sys.executable, "-m", "dvc"]
STAGES = ("generate", "train", "evaluate")

#: Two plants of the ablation set, two step amplitudes (+-1, +-2), 2 s per trajectory, one
#: epoch, a 3 s unit-step evaluation only. Each entry is one `dvc exp run -S` argument.
TINY = [
    "conf/systems/all.yaml:include=[double_integrator,mass_spring_damper]",
    "conf/data/demos.yaml:duration=2.0",
    "conf/data/demos.yaml:amplitudes.segments=[{start:1.0,stop:2.0,step:1.0}]",
    "conf/trainer/default.yaml:max_epochs=1",
    "conf/trainer/default.yaml:num_sanity_val_steps=0",
    "conf/trainer/default.yaml:enable_progress_bar=false",
    "conf/trainer/default.yaml:enable_model_summary=false",
    "conf/evaluation/default.yaml:scenarios.step.duration=3.0",
    *(f"conf/evaluation/default.yaml:~scenarios.{s}" for s in ("random_steps", "sine", "ramp")),
    "conf/evaluation/default.yaml:~scenarios.composite",
    *(
        f"conf/evaluation/default.yaml:~scenarios.{s}"
        for s in (
            "staircase",
            "frequency_sweep",
            "random_initial",
            "actuator_gain_120pct",
            "actuator_gain_80pct",
            "state_noise",
        )
    ),  # fmt: skip  (the rest apply to other plants)
    "conf/data/demos.yaml:~families",  # the paper's steps only: two plants x four steps
    "conf/report/default.yaml:gate.duration=3.0",
    # the primary config and the model config are edited the same way (no interpolations)
    "conf/model/generalist.yaml:hidden=16",
    "conf/config.yaml:dagger=null",
    "conf/config.yaml:closed_loop_val.duration=2.0",
]


def sh(cmd: list[str], cwd: Path, env: dict[str, str]) -> str:
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"{cmd}:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    return proc.stdout + proc.stderr


@pytest.fixture
def repo(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """The project's pipeline files, committed in a fresh git + DVC repository."""
    work = tmp_path / "repo"
    work.mkdir()
    for item in ("src", "conf", "dvc.yaml", ".gitignore", "ablation"):
        src = ROOT / item
        if src.is_dir():
            ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
            shutil.copytree(src, work / item, ignore=ignore)
        else:
            shutil.copy(src, work / item)
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONPATH": str(work / "src"),
        "OMP_NUM_THREADS": "1",
        "DVC_NO_ANALYTICS": "1",
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@t",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@t",
    }
    for key in ("GC_CONF_DIR", "MLFLOW_TRACKING_URI"):  # the embedded defaults, in `work`
        env.pop(key, None)
    # no MLflow model of each training (tests/test_train.py logs one): a text edit, as
    # `-S` cannot set a key of a file with interpolations (conf/logger/mlflow.yaml)
    logger = work / "conf/logger/mlflow.yaml"
    text = logger.read_text()
    assert "log_model: true " in text, "conf/logger/mlflow.yaml changed: update this edit"
    logger.write_text(text.replace("log_model: true ", "log_model: false", 1))
    sh(["git", "init", "-q"], work, env)
    sh([*DVC, "init", "-q"], work, env)
    sh(["git", "add", "-A"], work, env)
    sh(["git", "commit", "-qm", "project"], work, env)
    return work, env


@pytest.mark.slow
def test_tiny_pipeline_runs_once_then_skips(repo):
    work, env = repo
    args = [a for s in TINY for a in ("-S", s)]
    out = sh([*DVC, "exp", "run", *args], work, env)
    for stage in STAGES:
        assert f"Running stage '{stage}'" in out, out[-3000:]

    manifest = json.loads((work / "data/demos/manifest.json").read_text())
    assert manifest["n_trajectories"] == 2 * 4
    assert (work / "models/policy.ckpt").is_file()
    assert "quality_bar" in json.loads((work / "reports/eval/summary.json").read_text())
    assert not (work / "reports/ablation").exists()  # the ablation is ablation/dvc.yaml's
    policy, _ = load_policy(work / "models/policy.ckpt")
    assert policy.config["hidden"] == 16  # the -S edit of conf/model reached the training

    again = sh([*DVC, "repro"], work, env)
    for stage in STAGES:
        assert f"Stage '{stage}' didn't change, skipping" in again, again
    assert "Running stage" not in again  # the ablation pipeline is not part of `dvc repro`

    # the ablation of the paper's recipe (the default recipe's stages differ by its data and
    # `experiment`: tests/test_ablation_dvc.py composes both), its points trimmed to d32 and
    # m5 and its 60 epochs to one: scripts/ablation.sh trains and evaluates them two at a
    # time, then the report
    _tiny_ablation(work, env)
    out = sh(["bash", "scripts/ablation.sh", "paper"], work, env)
    assert "ablation/dvc.yaml:default@" not in out
    for recipe in ("paper",):
        for point in ("d32", "m5"):
            assert f"Running stage 'ablation/dvc.yaml:{recipe}@{point}'" in out, out[-3000:]
            assert (work / f"ablation/models/{recipe}/{point}/policy.ckpt").is_file()
            assert (work / f"ablation/reports/{recipe}/{point}/summary.json").is_file()
        report = work / "ablation/report" / recipe
        summary = json.loads((report / "summary.json").read_text())
        assert summary["recipe"] == recipe  # read from the runs' params
        runs = pd.read_csv(report / "runs.csv").set_index("label")
        assert runs.loc["M=5", "status"] == "ok" and runs.loc["d=32", "status"] == "ok"
        assert runs.loc["d=16", "status"] == "no run" and runs.loc["M=5", "experts"] == 5
        points = pd.read_csv(report / "points.csv")
        assert len(points) == 2 and (points["bar_checked"] > 0).all()  # evaluations matched
        assert len(pd.read_csv(report / "claims.csv")) == 22
        gates = pd.read_csv(report / "gate_weights.csv", index_col=0)
        assert list(gates.columns) == [f"expert_{i}" for i in range(1, 6)] and len(gates) == 2
        key = read_tables(report).key  # its figures drawn from its tables, as make results does
        assert all(figure_key(report / f"{n}.png") == key for n in FIGURES), recipe
    with sqlite3.connect(work / "mlflow.db") as db:
        rows = db.execute(
            "select r.name, t.value from runs r join tags t on t.run_uuid = r.run_uuid "
            "join experiments e on e.experiment_id = r.experiment_id "
            "where e.name = 'generalist-control/ablation' and t.key = 'mlflow.parentRunId'"
        ).fetchall()
        parents = dict(
            db.execute(
                "select r.run_uuid, r.name from runs r join tags t on t.run_uuid = r.run_uuid "
                "where t.key = 'gc.role' and t.value = 'group'"
            ).fetchall()
        )
        names = dict(db.execute("select run_uuid, name from runs").fetchall())
        evaluated = db.execute(
            "select count(distinct run_uuid) from metrics where key = 'eval/bar_passed'"
        ).fetchone()[0]
    # every training under its recipe's one parent, in one experiment, its verdicts logged
    # in an evaluation run of its own nested under the training run
    assert sorted(parents.values()) == ["ablation:paper"]
    by_parent = sorted((parents[p], name) for name, p in rows if p in parents)
    nested = {p for _, p in rows if p not in parents}
    assert sorted(names[p] for p in nested) == [name for _, name in by_parent]
    assert by_parent == [("ablation:paper", "paper-d32"), ("ablation:paper", "paper-m5")]
    assert evaluated >= 2


def _tiny_ablation(work: Path, env: dict[str, str]) -> None:
    """The ablation pipeline on two points, the paper's recipe at one epoch, its tiny data."""
    pipeline = work / "ablation" / "dvc.yaml"
    text = pipeline.read_text()
    head, rest = text.split("  - points:\n", 1)
    body = rest[rest.index("\nstages:") :]
    points = "  - points:\n      d32: {hidden: 32, experts: 3, seed: 42}\n"
    points += "      m5: {hidden: 32, experts: 5, seed: 42}\n"
    pipeline.write_text(head + points + body)
    paper = work / "conf/experiment/paper.yaml"
    paper.write_text(paper.read_text().replace("max_epochs: 60", "max_epochs: 1"))
    (work / "scripts").mkdir(exist_ok=True)
    shutil.copy(ROOT / "scripts" / "ablation.sh", work / "scripts")
    # the paper's data is in git in the project; here, the tiny configuration's
    sh([sys.executable, "-m", "generalist_control.generate", "experiment=paper"], work, env)
