"""The stages' ``@stage_main``: Hydra's runs and multiruns, the config composed once per run."""

from __future__ import annotations

import logging
import shutil
import sys
from pathlib import Path

import pytest
from hydra._internal.hydra import Hydra
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig

from generalist_control.common.paths import conf_dir
from generalist_control.common.stage_main import stage_main


def _main(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, *args: str, conf: Path | None = None
) -> tuple[list, int]:
    """Run a stage-shaped task with ``args`` on the command line: (its calls, compositions).

    ``conf``: ``GC_CONF_DIR``, set once the task is defined (as a command sets it before it
    runs a stage whose module was imported earlier).
    """
    calls: list = []
    composed = [0]
    original = Hydra.compose_config

    def counting(self, *a, **k):
        composed[0] += 1
        return original(self, *a, **k)

    @stage_main("config")
    def task(cfg):
        calls.append((cfg.seed, str(HydraConfig.get().mode)))

    monkeypatch.setattr(Hydra, "compose_config", counting)
    if conf is not None:
        monkeypatch.setenv("GC_CONF_DIR", str(conf))
    where = [f"hydra.run.dir={tmp_path / 'run'}", f"hydra.sweep.dir={tmp_path / 'multi'}"]
    monkeypatch.setattr(sys, "argv", ["stage", *args, *where, "hydra.output_subdir=null"])
    GlobalHydra.instance().clear()
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        task()
    finally:  # Hydra's run configured logging for the process: the tests after it get theirs
        GlobalHydra.instance().clear()
        for handler in set(root.handlers) - set(handlers):
            root.removeHandler(handler)
            handler.close()
        for handler in handlers:
            if handler not in root.handlers:
                root.addHandler(handler)
        root.setLevel(level)
    return calls, composed[0]


def test_a_run_composes_the_config_once(monkeypatch, tmp_path):
    calls, composed = _main(monkeypatch, tmp_path, "seed=7")
    assert calls == [(7, "RunMode.RUN")]
    assert composed == 1  # Hydra's hydra.main alone composes twice (get_mode, then run)
    assert Hydra.get_mode.__module__ == "hydra._internal.hydra"  # put back afterwards


def test_the_config_folder_is_the_one_named_when_the_stage_runs(monkeypatch, tmp_path):
    conf = tmp_path / "conf"
    shutil.copytree(conf_dir(), conf)
    text = (conf / "config.yaml").read_text()
    (conf / "config.yaml").write_text(text.replace("\nseed: 42", "\nseed: 5", 1))
    calls, _ = _main(monkeypatch, tmp_path, conf=conf)
    assert calls == [(5, "RunMode.RUN")]  # 42 from the folder of the import


def test_a_multirun_by_flag_or_by_override_runs_every_point(monkeypatch, tmp_path):
    calls, _ = _main(monkeypatch, tmp_path, "-m", "seed=1,2")
    assert calls == [(1, "RunMode.MULTIRUN"), (2, "RunMode.MULTIRUN")]
    # the mode named by an override is read by Hydra's own get_mode, as without stage_main
    calls, _ = _main(monkeypatch, tmp_path / "o", "hydra.mode=MULTIRUN", "seed=3")
    assert calls == [(3, "RunMode.MULTIRUN")]


def test_a_config_passed_in_skips_hydra(monkeypatch):
    seen = []

    @stage_main("config")
    def task(cfg):
        seen.append(cfg)
        return 5

    assert task({"seed": 1}) == 5 and seen == [{"seed": 1}]
