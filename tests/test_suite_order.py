"""The suite hands out its files longest first (tests/conftest.py, tests/durations.json),
and `make test` runs mypy beside it."""

from __future__ import annotations

import json
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_the_collected_files_run_longest_first(request: pytest.FixtureRequest):
    seconds = json.loads((REPO / "tests" / "durations.json").read_text())
    files = list(dict.fromkeys(i.nodeid.split("::")[0] for i in request.session.items))
    timed = [f for f in files if f in seconds]
    assert timed == sorted(timed, key=lambda f: -seconds[f])  # longest first ...
    assert files[: len(timed)] == timed  # ... and before every file the table lacks


def test_the_make_targets_keep_that_order():
    """xdist reorders whole files by their number of tests unless told not to."""
    makefile = (REPO / "Makefile").read_text()
    for target in ("test:", "test-fast:"):
        recipe = makefile.split(f"\n{target}", 1)[1].split("\n\n", 1)[0]
        assert "--dist loadfile --no-loadscope-reorder" in recipe, target


def test_durations_are_summed_by_file_from_pytests_report(tmp_path):
    report = tmp_path / "out.txt"
    report.write_text(
        "===== slowest durations =====\n"
        "12.50s call     tests/test_a.py::test_x[1]\n"
        "2.00s setup    tests/test_a.py::test_x[1]\n"
        "20.00s call     tests/test_b.py::test_y\n"
        "0.10s teardown tests/test_c.py::Test::test_z\n"
    )
    out = tmp_path / "durations.json"
    runpy.run_path(str(REPO / "scripts" / "test_durations.py"))["main"](str(report), out)
    table = json.loads(out.read_text())
    assert table == {"tests/test_b.py": 20.0, "tests/test_a.py": 14.5, "tests/test_c.py": 0.1}
    assert list(table) == ["tests/test_b.py", "tests/test_a.py", "tests/test_c.py"]


def test_a_report_without_durations_is_refused(tmp_path):
    report = tmp_path / "out.txt"
    report.write_text("5 passed in 1.00s\n")
    script = REPO / "scripts" / "test_durations.py"
    proc = subprocess.run([sys.executable, str(script), str(report)], capture_output=True,
                          text=True)  # fmt: skip
    assert proc.returncode == 1 and "run pytest with --durations=0" in proc.stderr


def _fake_venv(folder: Path, mypy_rc: int, pytest_rc: int) -> Path:
    """A venv's bin/ whose ruff passes, mypy and pytest exit as told."""
    folder.mkdir()
    scripts = {
        "ruff": "exit 0",
        "mypy": f"echo 'src/x.py:1: error: a type error'; exit {mypy_rc}",
        "python": f"echo 'pytest ran'; exit {pytest_rc}",
    }
    for name, body in scripts.items():
        (folder / name).write_text(f"#!/bin/sh\n{body}\n")
        (folder / name).chmod(0o755)
    return folder


@pytest.mark.parametrize(
    ("mypy_rc", "pytest_rc", "rc"), [(1, 0, 1), (0, 3, 3), (1, 3, 3), (0, 0, 0)]
)
def test_make_test_fails_when_mypy_or_the_tests_fail(tmp_path, mypy_rc, pytest_rc, rc):
    """mypy runs beside the tests; its report follows theirs and its failure fails the target."""
    venv = _fake_venv(tmp_path / "bin", mypy_rc, pytest_rc)
    proc = subprocess.run(
        ["make", "-s", "-o", "setup", "test", f"VENV={venv}"],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == (2 if rc else 0), proc.stderr  # make's own status on a failure
    assert f"Error {rc}" in proc.stderr if rc else proc.stderr == ""
    out = proc.stdout
    assert out.index("pytest ran") < out.index("mypy:") < out.index("a type error")
