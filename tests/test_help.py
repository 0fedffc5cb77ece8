"""``--help`` of every entry point: one short page, not the whole composed config."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from helpers import run_command

REPO = Path(__file__).resolve().parents[1]

#: Each a subprocess of several seconds: train's in the fast tests, the others marked slow.
COMMANDS = [
    pytest.param("train", ["train.py", "experts=5", "model.hidden=64"], id="train"),
    pytest.param("tune", ["tune.py"], id="tune", marks=pytest.mark.slow),
    pytest.param(
        "evaluate", ["-m", "generalist_control.evaluate"], id="evaluate", marks=pytest.mark.slow
    ),
]


def _help(*args: str) -> str:
    out = run_command([sys.executable, *args, "--help"], cwd=REPO, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout


@pytest.mark.parametrize(("name", "args"), COMMANDS)
def test_help_is_one_short_page_that_says_how_to_see_the_config(name, args):
    text = _help(*args)
    lines = text.splitlines()
    assert len(lines) < 60, f"{len(lines)} lines"
    assert lines[0].startswith(f"{name}: ")
    assert "--cfg job" in text
    for group in ("experiment: ", "systems: ", "trainer: "):  # Hydra's list of the groups
        assert any(line.startswith(group) for line in lines), group
    for key in ("experts", "model.hidden", "trainer.max_epochs", "paths.data_dir"):
        assert f"  {key} " in text, key
    assert "_target_" not in text  # no config dump
    if name == "train":  # the values, with the command's overrides
        assert "(now 5)" in text and "(now 64)" in text
