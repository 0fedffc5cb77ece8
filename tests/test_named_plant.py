"""A named plant is one YAML file in conf/plants/ and its line in a set: nothing else changes.

In a copy of ``conf/`` (``GC_CONF_DIR``) a plant file with the next tag and its line in
``conf/systems/all.yaml`` are the only changes; the stages' own commands then generate its
data, train a (tiny) policy with a row for it and evaluate the policy on it.
"""

from __future__ import annotations

import filecmp
import os
import shutil
import sys
from pathlib import Path

import pandas as pd
import pytest

from generalist_control.common.paths import conf_dir
from generalist_control.data.demos import read_manifest
from generalist_control.model.policy import load_policy
from helpers import run_command

REPO = Path(__file__).resolve().parents[1]

PLANT = """\
tag: 25
description: "Motor-driven cart, position output"
source: "Franklin et al., Feedback Control of Dynamic Systems, Ex. 2.1; parameters chosen"
dt: 0.05
states:
  - {name: position, unit: "cm"}
  - {name: velocity, unit: "cm/s"}
input: {name: force, unit: "N"}
output: {name: position, unit: "cm"}
A: [[0.0, 1.0], [0.0, -2.0]]
B: [[0.0], [50.0]]
C: [[1.0, 0.0]]
lqi:
  Q: [1.0, 0.0, 1.0]
  R: 1.0
"""
LINE = "  - /plants@plants.my_plant: my_plant\n"
SET = "systems.include=[cstr,my_plant]"


def _changed(a: Path, b: Path) -> list[str]:
    """Files that differ, or exist on one side only, between two trees (relative paths)."""
    cmp = filecmp.dircmp(a, b)
    out = [*cmp.left_only, *cmp.right_only, *cmp.diff_files, *cmp.funny_files]
    for sub in cmp.subdirs:
        out += [f"{sub}/{p}" for p in _changed(a / sub, b / sub)]
    return sorted(out)


def _run(module: str, tmp: Path, env: dict[str, str], *overrides: str) -> str:
    cmd = [sys.executable, "-m", f"generalist_control.{module}", *overrides]
    cmd.append(f"hydra.run.dir={tmp / 'hydra' / module}")
    proc = run_command(cmd, cwd=REPO, env=env, timeout=900)
    assert proc.returncode == 0, (module, proc.stderr[-3000:])
    return proc.stdout + proc.stderr


@pytest.mark.slow
def test_a_plant_file_and_its_line_generate_train_and_evaluate(tmp_path):
    conf = tmp_path / "conf"
    shutil.copytree(conf_dir(), conf)
    (conf / "plants" / "my_plant.yaml").write_text(PLANT)
    all_set = conf / "systems" / "all.yaml"
    text = all_set.read_text()
    anchor = "  - /plants@plants.f16_pitch: f16_pitch\n"
    all_set.write_text(text.replace(anchor, anchor + LINE))
    assert _changed(conf_dir(), conf) == ["plants/my_plant.yaml", "systems/all.yaml"]

    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env.update(GC_CONF_DIR=str(conf), OMP_NUM_THREADS="1")
    data, models, reports = tmp_path / "demos", tmp_path / "models", tmp_path / "reports"
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    tiny = ["data.duration=2.0", "data.families=null",
            "data.amplitudes.segments=[{start:1.0,stop:4.0,step:1.0}]"]  # fmt: skip
    _run("generate", tmp_path, env, SET, *tiny, f"paths.data_dir={data}")
    assert read_manifest(data)["plants"]["my_plant"]["tag"] == 25
    _run("train", tmp_path, env, SET, *tiny, f"paths.data_dir={data}",
         f"paths.models_dir={models}", f"run_dir={tmp_path / 'run'}",
         f"logger.tracking_uri={uri}", "logger.experiment_name=named",
         f"logger.artifact_location={tmp_path / 'mlruns'}", "logger.log_model=false",
         "trainer.accelerator=cpu", "trainer.max_epochs=2", "trainer.enable_progress_bar=false",
         "trainer.enable_model_summary=false", "dagger=null",
         "closed_loop.systems=[cstr,my_plant]", "closed_loop.duration=3.0")  # fmt: skip
    policy, meta = load_policy(models / "policy.ckpt")
    assert policy.net.n_tags == 26  # one row per catalogue plant, the new one's included
    assert meta["tags"] == {"cstr": 10, "my_plant": 25}
    step = "+evaluation.scenarios={step:{kind:step,duration:5.0}}"
    _run("evaluate", tmp_path, env, SET, f"policy={models / 'policy.ckpt'}",
         f"paths.reports_dir={reports}", f"logger.tracking_uri={uri}",
         "logger.experiment_name=named", "evaluation.plots=false", "evaluation.backend=torch",
         "~evaluation.scenarios", step)  # fmt: skip
    df = pd.read_csv(reports / "metrics.csv")
    assert set(df.system) == {"cstr", "my_plant"}
    mine = df[df.system == "my_plant"]
    assert set(mine.controller) == {"GC", "LQI", "LQI-AW"}
    lqi = mine[(mine.controller == "LQI") & (mine.metric == "diverged")]
    assert (lqi.value == 0).all() and len(lqi) > 0
