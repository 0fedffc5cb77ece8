"""scripts/setup.sh: the CPU build of torch, from the configured sources or PyTorch's CPU index.

The script's decision is tested through its functions (the script, sourced, runs nothing),
with pip's answer faked, so no torch is reinstalled; the real probe runs against this
machine's configured sources, where the CPU wheel lies on local disk.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "setup.sh"
CPU_INDEX = "https://download.pytorch.org/whl/cpu"


def _bash(code: str, **env: str) -> subprocess.CompletedProcess:
    """Run ``code`` in bash after sourcing the script, with this interpreter's ``python``."""
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]])
    return subprocess.run(
        ["bash", "-c", f". {SCRIPT}\n{code}"],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PATH": path, **env},
        cwd=REPO,
    )


def _args(fake_probe: str, os_name: str = "Linux") -> list[str]:
    out = _bash(f"torch_findable() {{ {fake_probe}; }}\ntorch_install_args {os_name}")
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_the_script_parses():
    assert subprocess.run(["bash", "-n", str(SCRIPT)], capture_output=True).returncode == 0


def test_a_cpu_wheel_in_the_configured_sources_is_taken_from_there():
    assert _args("return 0") == ["torch==2.13.0+cpu"]


def test_elsewhere_on_linux_the_cpu_index_is_named():
    args = _args("return 1")
    assert args[args.index("--index-url") + 1] == CPU_INDEX
    assert args[-1] == "torch==2.13.0"
    assert "--timeout" in args


def test_the_cpu_index_can_be_overridden():
    out = _bash("torch_findable() { return 1; }\ntorch_install_args Linux", TORCH_CPU_INDEX="x")
    assert out.stdout.split()[:2] == ["--index-url", "x"]


def test_on_macos_pypi_torch_is_the_cpu_build():
    assert _args("return 1", "Darwin") == ["torch==2.13.0"]


def test_the_probe_finds_what_pip_can_install_and_only_that():
    """Against the real configured sources: the local CPU wheel, not a version that is not."""
    here = _bash("torch_findable torch==2.13.0+cpu && echo yes || echo no")
    if "no" in here.stdout:
        pytest.skip("pip's configured sources hold no torch 2.13.0+cpu on this machine")
    assert here.stdout.split() == ["yes"]
    absent = _bash("torch_findable torch==2.13.0+nosuchbuild && echo yes || echo no")
    assert absent.stdout.split() == ["no"]


def test_the_probe_is_bounded_in_time(tmp_path):
    """A pip that hangs (an unreachable index) counts as "not there" after GC_PROBE_TIMEOUT."""
    fake = tmp_path / "python"
    fake.write_text("#!/bin/sh\nsleep 30\n")
    fake.chmod(0o755)
    start = time.monotonic()
    out = _bash(
        f"PATH={tmp_path}:$PATH\ntorch_findable x && echo yes || echo no", GC_PROBE_TIMEOUT="1"
    )
    assert out.stdout.split() == ["no"]
    assert time.monotonic() - start < 20


PIP_LINE = "+ python -m pip install -q -e .[dev]"
UV_LINE = "+ python -m uv pip install -q --python {} --compile-bytecode -e .[dev]"


def _dry_run(**env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["bash", str(SCRIPT)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "GC_SETUP_DRY_RUN": "1", **env},
        cwd=REPO,
    )


@pytest.mark.parametrize("installer", ["uv", "pip"])
def test_dry_run_prints_the_commands_and_installs_nothing(installer):
    """The project's requirements go through uv where the environment has it, else pip."""
    out = _dry_run(GC_INSTALLER=installer)
    assert out.returncode == 0, out.stderr
    venv = REPO / ".venv" / "bin" / "python"  # the script's python: the venv's, else PATH's
    python = str(venv) if venv.is_file() else shutil.which("python")
    has_uv = subprocess.run([python, "-m", "uv", "--version"], capture_output=True)
    if installer == "uv" and has_uv.returncode == 0:
        assert UV_LINE.format(python) in out.stdout
        assert PIP_LINE not in out.stdout
    else:
        assert PIP_LINE in out.stdout and "uv pip" not in out.stdout
    assert "setup done" not in out.stdout


def test_pip_installs_the_requirements_when_uv_fails():
    """uv answers but fails (say, an index it cannot reach): pip installs instead."""
    fake = 'uv_ready() { return 0; }\nrun() { echo "+ $*"; [ "$3" != uv ]; }\ninstall_project'
    out = _bash(fake)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0].startswith("+ python -m uv pip install") and lines[1] == PIP_LINE
    assert "trying pip" in out.stderr
