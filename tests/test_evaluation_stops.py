"""An evaluation stopped by a signal: no process left, nothing half-published, its run ended.

The command runs for real (the LQI law as the policy, a few plants, figures on) and is
signalled while a forked child of it works (a share of the plants, or of the figures); the
whole evaluations around it run through the tests' fork server (``helpers.run_command``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest

from generalist_control.model.policy import save_policy
from generalist_control.simulation.lqi import design_lqi
from helpers import lqi_law_policy, run_command

REPO = Path(__file__).resolve().parents[1]
PLANTS = ["cstr", "two_tank", "dc_motor_speed", "unstable", "hydraulic_actuator"]

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux's /proc"),
]


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _command(tmp_path: Path, uri: str) -> tuple[list[str], dict[str, str]]:
    pol, meta = lqi_law_policy(PLANTS, design_lqi)
    policy = save_policy(tmp_path / "policy.ckpt", pol, meta)
    cmd = [
        sys.executable, "-m", "generalist_control.evaluate", f"policy={policy}",
        f"systems.include=[{','.join(PLANTS)}]", f"paths.reports_dir={tmp_path / 'eval'}",
        f"logger.tracking_uri={uri}", f"logger.experiment_prefix={tmp_path.name}",
        "evaluation.backend=torch", f"hydra.run.dir={tmp_path / 'hydra'}",
    ]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1", "TMPDIR": str(tmp_path / "temp")}
    env.pop("MLFLOW_TRACKING_URI", None)
    (tmp_path / "temp").mkdir()
    return cmd, env


def _forked(pid: int) -> list[int]:
    """Children of ``pid`` that are forks of it (its command line), not programs it runs."""
    try:
        own = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return []
    out = []
    for child in _children(pid):
        try:
            if Path(f"/proc/{child}/cmdline").read_bytes() == own:
                out.append(child)
        except OSError:
            pass
    return out


def _signal_once_forked(cmd: list[str], env: dict[str, str], sig: int) -> tuple[int, list[int]]:
    """Run ``cmd``; send ``sig`` once a fork of it has worked a while. Its exit code, children.

    A fork that lives a second is the evaluation's (a share of the plants or of the figures),
    not the instant between a fork and the program it runs (``uname``, ``git``).
    """
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)  # fmt: skip
    first: dict[int, float] = {}
    deadline = time.monotonic() + 600
    while proc.poll() is None and time.monotonic() < deadline:
        now = time.monotonic()
        forks = _forked(proc.pid)
        first = {c: first.get(c, now) for c in forks}
        if any(now - t > 1.0 for t in first.values()):
            break
        time.sleep(0.02)
    assert first, "the evaluation ended before it forked"
    children = _children(proc.pid)
    proc.send_signal(sig)
    return proc.wait(timeout=300), children


def _gone(pids: list[int], seconds: float = 10) -> bool:
    deadline = time.monotonic() + seconds
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    return not any(_alive(p) for p in pids)


def test_a_signal_ends_the_evaluation_non_zero_its_run_killed_nothing_left(tmp_path):
    """SIGTERM; Ctrl-C takes the same path (``exiting_on_signals``: tests/test_stop_signals.py)."""
    sig = signal.SIGTERM
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cmd, env = _command(tmp_path, uri)
    done = run_command([*cmd, "evaluation.plots=false"], cwd=REPO, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    before = {p.name: p.read_bytes() for p in (tmp_path / "eval").iterdir()}
    code, children = _signal_once_forked(cmd, env, sig)
    assert code == 143
    assert _gone(children), "a forked child outlived the evaluation"
    assert {p.name: p.read_bytes() for p in (tmp_path / "eval").iterdir()} == before
    assert not [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name]
    assert not list((tmp_path / "temp").iterdir())
    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name(f"{tmp_path.name}/evaluate")
    runs = client.search_runs([exp.experiment_id], order_by=["attributes.start_time DESC"])
    assert [r.info.status for r in runs] == ["KILLED", "FINISHED"]
    assert f"stopped by {sig.name}" in (tmp_path / "hydra" / "evaluate.log").read_text()


def test_sigkill_leaves_no_process_and_the_next_evaluation_cleans_up(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cmd, env = _command(tmp_path, uri)
    code, children = _signal_once_forked(cmd, env, signal.SIGKILL)
    assert code == -signal.SIGKILL
    assert _gone(children), "a forked child outlived the evaluation"
    done = run_command([*cmd, "evaluation.plots=false"], cwd=REPO, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert not [p.name for p in tmp_path.iterdir() if ".tmp-" in p.name]
    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name(f"{tmp_path.name}/evaluate")
    runs = client.search_runs([exp.experiment_id], order_by=["attributes.start_time DESC"])
    assert [r.info.status for r in runs] == ["FINISHED", "KILLED"]  # ended by the next one
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert summary["quality_bar"]["stable_everywhere"] is True
