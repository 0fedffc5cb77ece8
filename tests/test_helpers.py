"""The tests' own helpers do what they stand for.

The fork server (tests/zygote.py) runs a command as a real process would; ``compose_cfg``
gives what Hydra's ``compose`` gives.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

import helpers
from generalist_control.common.paths import conf_dir
from helpers import REAL_PROCESSES_ENV, compose_cfg, run_command

PROBE = Path(__file__).with_name("zygote_probe.py")


@pytest.fixture(autouse=True)
def the_fork_server_on(monkeypatch):
    """These tests are the fork server's, whatever ``GC_TEST_REAL_PROCESSES`` says."""
    monkeypatch.delenv(REAL_PROCESSES_ENV, raising=False)


def _both(*args: str, tmp_path: Path, **extra: str) -> tuple:
    """The probe run through the fork server and as a real process, from ``tmp_path``."""
    env = {**os.environ, "GC_PROBE": "seen", **extra}
    cmd = [sys.executable, str(PROBE), *args]
    forked = run_command(cmd, cwd=tmp_path, env=env, timeout=60)
    real = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    return forked, real


@pytest.mark.parametrize(("code", "threads"), [("0", {}), ("3", {"OMP_NUM_THREADS": "1"})])
def test_a_command_sees_what_a_real_process_sees(tmp_path, code, threads):
    assert helpers._runs_in_zygote([sys.executable, str(PROBE)], str(tmp_path), dict(os.environ))
    forked, real = _both(code, "x=1", tmp_path=tmp_path, **threads)
    assert forked.returncode == real.returncode == int(code)
    seen = json.loads(forked.stdout)
    assert seen == json.loads(real.stdout)
    assert seen["argv"] == [code, "x=1"] and seen["cwd"] == str(tmp_path)
    assert seen["name"] == "__main__" and seen["path0"] == str(PROBE.parent)
    assert seen["probe"] == "seen" and (seen["threads"] == 1) is bool(threads)
    assert forked.stderr == real.stderr == "to stderr\n"


def test_an_exception_is_reported_as_the_interpreter_reports_it(tmp_path):
    forked, real = _both("raise", tmp_path=tmp_path)
    assert forked.returncode == real.returncode == 1
    assert forked.stderr.splitlines()[-1] == real.stderr.splitlines()[-1]
    assert real.stderr.splitlines()[-1] == "RuntimeError: the probe raised"


def test_a_timeout_kills_the_command_and_raises(tmp_path):
    with pytest.raises(subprocess.TimeoutExpired):
        run_command([sys.executable, str(PROBE), "sleep"], cwd=tmp_path, timeout=2)
    # the server answers the next command
    assert run_command([sys.executable, str(PROBE), "0"], cwd=tmp_path).returncode == 0


def test_other_commands_and_the_switch_run_real_processes(tmp_path, monkeypatch):
    env = dict(os.environ)
    assert not helpers._runs_in_zygote([sys.executable, "-c", "pass"], str(tmp_path), env)
    assert not helpers._runs_in_zygote(["git", "status"], str(tmp_path), env)
    copy = tmp_path / "src" / "generalist_control"
    copy.mkdir(parents=True)  # another copy of the package on PYTHONPATH: a fresh process
    other = {**env, "PYTHONPATH": str(tmp_path / "src")}
    assert not helpers._runs_in_zygote([sys.executable, "-m", "generalist_control.train"],
                                       str(tmp_path), other)  # fmt: skip
    monkeypatch.setenv(REAL_PROCESSES_ENV, "1")
    assert not helpers._runs_in_zygote([sys.executable, str(PROBE)], str(tmp_path), env)


def _hydra(*overrides: str):
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@pytest.mark.parametrize(
    "overrides",
    [
        (),
        ("model.hidden=32.9", "experiment=paper"),  # a value, then a config chosen after it
        ("+dagger.focus=2", "~evaluation.scenarios", "closed_loop.systems=[]"),
        ("+evaluation.scenarios={step:{kind:step,duration:5.0}}", "experts=5"),
        ("data.families=null", "systems=paper", "systems.include=[cstr,hydraulic_actuator]"),
        ("model/plant=inferred", "dagger=null"),
        ("+plants@systems.plants.my_plant=cstr",),
    ],
)
def test_compose_cfg_is_hydras_compose(overrides):
    got, want = compose_cfg(*overrides), _hydra(*overrides)
    assert OmegaConf.to_container(got) == OmegaConf.to_container(want)
    assert OmegaConf.is_struct(got) and OmegaConf.is_struct(want)


@pytest.mark.parametrize("override", ["model.nope=1", "+model.hidden=3", "~model.nope"])
def test_compose_cfg_refuses_as_hydra_does(override):
    with pytest.raises(ConfigCompositionException) as want:
        _hydra(override)
    with pytest.raises(ConfigCompositionException) as got:
        compose_cfg(override)
    assert str(got.value) == str(want.value)
