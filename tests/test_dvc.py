"""The DVC `generate` stage in a throw-away git repository, and push/pull to a local remote."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
DVC = [sys.executable, "-m", "dvc"]


def sh(cmd, cwd, env):
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"{cmd}: {proc.stdout}\n{proc.stderr}"
    return proc.stdout + proc.stderr


@pytest.fixture
def repo(tmp_path):
    """A copy of the project's pipeline files in a fresh git + DVC repository."""
    work = tmp_path / "repo"
    work.mkdir()
    for item in ("src", "conf", "dvc.yaml"):
        src = ROOT / item
        if src.is_dir():
            shutil.copytree(src, work / item, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(src, work / item)
    env = {
        **os.environ,
        "PYTHONPATH": str(work / "src"),
        "DVC_NO_ANALYTICS": "1",
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@t",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@t",
    }
    env.pop("GC_CONF_DIR", None)
    sh(["git", "init", "-q"], work, env)
    sh([*DVC, "init", "-q"], work, env)
    return work, env


def test_repro_skip_rerun_push_pull(repo, tmp_path):
    work, env = repo
    out = sh([*DVC, "repro", "generate"], work, env)
    assert "Running stage 'generate'" in out
    manifest = json.loads((work / "data/demos/manifest.json").read_text())
    families = yaml.safe_load((work / "conf/data/demos.yaml").read_text())["families"]
    assert manifest["n_trajectories"] == 25 * (64 + sum(f["count"] for f in families.values()))
    assert "didn't change, skipping" in sh([*DVC, "repro", "generate"], work, env)

    # changing the amplitude grid re-runs the stage
    grid = work / "conf/data/demos.yaml"
    grid.write_text(
        grid.read_text().replace(
            "{start: 15.0, stop: 20.0, step: 5.0}", "{start: 16.0, stop: 20.0, step: 4.0}"
        )
    )
    assert "Running stage 'generate'" in sh([*DVC, "repro", "generate"], work, env)
    changed = json.loads((work / "data/demos/manifest.json").read_text())
    assert changed["content_hash"] != manifest["content_hash"]

    # push to a local directory remote, lose cache and outputs, pull them back
    remote = tmp_path / "remote"
    sh([*DVC, "remote", "add", "-f", "-d", "tmpstore", str(remote)], work, env)
    sh([*DVC, "push", "generate"], work, env)
    assert any(remote.rglob("*"))
    shutil.rmtree(work / "data/demos")
    shutil.rmtree(work / ".dvc/cache")
    sh([*DVC, "pull", "generate"], work, env)
    pulled = json.loads((work / "data/demos/manifest.json").read_text())
    assert pulled["content_hash"] == changed["content_hash"]
    assert "didn't change, skipping" in sh([*DVC, "repro", "generate"], work, env)
