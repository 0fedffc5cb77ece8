"""Config values are taken as typed, never rounded or ignored, and checked before a run.

* the training's sections are read once into typed settings (``training.settings``) and the
  network's parts check their own arguments: non-integers, negative epochs, a learning rate
  the optimiser refuses, sections that do not fit together are refused before anything is
  logged or trained;
* ``generate`` refuses a plant tag outside ``0..model.plant.n_tags-1`` before writing, and
  catalogue tags that collide or leave a gap (``${gc.tag_count:}``: one row per plant file);
* the plant set (``systems``, ``systems.include``) selects the training plants even with
  DAgger and the closed-loop check off, and data without one of them is refused.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from omegaconf import OmegaConf

from generalist_control.common.paths import conf_dir
from generalist_control.common.sections import as_dict, require_int
from generalist_control.generate import run as generate_run
from generalist_control.model.policy import Policy, load_policy
from generalist_control.plants.catalog import (
    UnknownPlantError,
    available_plants,
    catalogue_tags,
    tag_count,
)
from generalist_control.plants.definition import PlantConfigError
from generalist_control.training.datamodule import (
    DemoDataModule,
    MissingPlantError,
    WindowTensors,
    split_by_trajectory,
)
from generalist_control.training.settings import LoaderSettings, read_training
from helpers import compose_cfg, config_section, run_command, tiny_train_overrides, train

REPO = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    return env


def _train_cfg(data_dir: Path, out: Path, *extra: str):
    uri = f"sqlite:///{out / 'mlflow.db'}"
    return compose_cfg(*tiny_train_overrides(data_dir, out, uri, "logger.log_model=false", *extra))


# ------------------------------------------------------------- typed once, before a run
def _refused(*overrides: str) -> str:
    """The message of the ValueError with which the training config is refused."""
    cfg = compose_cfg(*overrides)
    with pytest.raises(ValueError) as err:
        Policy(read_training(as_dict(cfg)).model)
    return str(err.value)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("model.hidden=32.9", "model.hidden must be an integer, got 32.9 (float)"),
        ("model.hidden=32.0", "model.hidden must be an integer, got 32.0 (float)"),
        ("model.hidden='32'", "model.hidden must be an integer, got '32' (str)"),
        ("model.hidden=true", "model.hidden must be an integer, got True (bool)"),
        ("model.heads=2.5", "model.heads must be an integer, got 2.5 (float)"),
        ("model.stride=1.5", "model.stride must be an integer, got 1.5 (float)"),
        ("model.plant.n_tags=25.5", "model.plant.n_tags must be an integer, got 25.5"),
        ("model.skip.samples=0.5", "model.skip.samples must be an integer, got 0.5"),
        ("model.law_history=2.5", "model.law_history must be an integer, got 2.5"),
        ("data.history=8.5", "data.history must be an integer, got 8.5 (float)"),
        ("model.window_scale=0.5", "model.window_scale must be 0 or 1 (false/true), got 0.5"),
        ("experts=2.5", "experts must be an integer, got 2.5 (float)"),
        ("experts=0", "experts must be a positive integer, got 0"),
        ("trainer.max_epochs=-1", "trainer.max_epochs must be a positive integer, got -1"),
        ("trainer.max_epochs=0", "trainer.max_epochs must be a positive integer, got 0"),
        ("threads=0", "threads must be a positive integer, got 0"),
        ("optimizer.lr=-0.1", "optimizer/scheduler refused: Invalid learning rate: -0.1"),
        ("loader.batch_size=10.5", "loader.batch_size must be an integer, got 10.5 (float)"),
        ("loader.val_fraction=1.5", "loader.val_fraction must lie in [0, 1), got 1.5"),
        ("dagger.beta=1.5", "dagger.beta must lie in [0, 1], got 1.5"),
        ("dagger.rounds=2.0", "dagger.rounds must be an integer, got 2.0"),
        ("+dagger.focus=2", "dagger has unknown keys ['focus']"),
        ("dagger.sampler.noise=-1", "dagger.sampler.noise must be a finite number >= 0"),
        ("+dagger.sampler.actuator={lag:nan,offset:0}", "actuator.lag must be a finite"),
        ("closed_loop_val=null", "monitor=val/closed_loop needs the closed-loop validation"),
        ("monitor=val/acc", "monitor must be val/loss or val/closed_loop"),
    ],
)
def test_a_bad_training_value_is_refused_naming_its_key(override, message):
    assert message in _refused(override)


def test_the_typed_settings_take_integers_of_any_kind_and_keep_the_config():
    cfg = compose_cfg("experiment=variants")
    settings = read_training(as_dict(cfg))
    assert settings.dagger is not None and settings.dagger.sampler.variants is not None
    assert settings.dagger.sampler.variants.fresh == 8 and settings.dagger.sampler.families == 0
    assert settings.closed_loop_val is not None and settings.closed_loop_val.duration == 30.0
    assert settings.scheduler is not None and settings.scheduler["T_max"] == 30
    assert settings.model["experts"] == 3 and settings.model["history"] == 8
    assert read_training(as_dict(compose_cfg("experiment=paper"))).dagger is None
    assert require_int("x", np.int64(0), minimum=0) == 0


def test_a_composition_without_the_package_still_works(tmp_path):
    """DVC's Hydra composes conf/ without importing the package."""
    code = (
        "from hydra import compose, initialize_config_dir\n"
        f"with initialize_config_dir({str(conf_dir())!r}, version_base='1.3'):\n"
        "    cfg = compose('config', overrides=['model.hidden=16', 'experiment=paper'])\n"
        "print(cfg.model.hidden, len(cfg.model.channels))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["16", "0"]


def test_train_py_with_a_fractional_size_fails_and_logs_nothing(tiny_data_dir, tmp_path):
    """The issue's command, ``python train.py model.hidden=32.9``, on tiny data."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    overrides = tiny_train_overrides(tiny_data_dir, tmp_path, uri)
    cmd = [sys.executable, "train.py", "model.hidden=32.9", *overrides]
    cmd.append(f"hydra.run.dir={tmp_path / 'hydra'}")
    proc = run_command(cmd, cwd=REPO, env=_env(), timeout=300)
    assert proc.returncode != 0
    assert "model.hidden must be an integer, got 32.9 (float)" in proc.stderr
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "models").exists()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("experts=2.5", r"experts must be an integer, got 2\.5 \(float\)"),
        ("loader.batch_size=10.5", r"loader\.batch_size must be an integer, got 10\.5 \(float\)"),
        ("trainer.max_epochs=-1", r"trainer\.max_epochs must be a positive integer, got -1"),
        ("optimizer.lr=nan", r"Invalid learning rate: nan"),
    ],
)
def test_train_refuses_a_bad_value_before_logging(tiny_data_dir, tmp_path, override, message):
    cfg = _train_cfg(tiny_data_dir, tmp_path, override)
    with pytest.raises(ValueError, match=message):
        train(cfg)
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "models").exists()


def test_train_refuses_a_fractional_model_size_composed_elsewhere(tiny_data_dir, tmp_path):
    """Whatever composed the config (a plain copy), the run-time check holds."""
    cfg = OmegaConf.create(OmegaConf.to_container(_train_cfg(tiny_data_dir, tmp_path)))
    cfg.model.hidden = 32.9
    with pytest.raises(ValueError, match=r"model\.hidden must be an integer, got 32\.9"):
        train(cfg)
    assert not (tmp_path / "mlflow.db").exists()


# ------------------------------------------------------------- item 8: tags and include
@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (
            ["systems.plants.cstr.tag=25"],
            r"plant 'cstr' \(tag 25\) is outside the policy's tags 0\.\.24 \(model\.plant\."
            r"n_tags=25\); raise model\.plant\.n_tags to at least 26 .* or give it a free tag "
            r"in 0\.\.24 "
            r"\(conf/plants/<name>\.yaml",
        ),
        # refused by the plant file check (plants/config.py), before the policy's range
        (["systems.plants.cstr.tag=-1"], r"plant 'cstr': field 'tag' must be a non-negative"),
        (
            ["model.plant.n_tags=10", "systems.include=[cstr,unstable]"],
            r"plants 'cstr' \(tag 10\), 'unstable' \(tag 11\) are outside the policy's tags "
            r"0\.\.9 \(model\.plant\.n_tags=10\); raise model\.plant\.n_tags to at least 12",
        ),
    ],
)
def test_generate_refuses_a_tag_the_policy_cannot_take(tmp_path, overrides, match):
    out = tmp_path / "demos"
    base = ["systems=paper", "systems.include=[cstr]", "data.duration=1.0"]
    cfg = compose_cfg(*base, f"paths.data_dir={out}", *overrides)
    with pytest.raises(PlantConfigError, match=match):
        generate_run(cfg)
    assert list(tmp_path.iterdir()) == []


def _conf_with_plant(tmp_path: Path, tag: int) -> Path:
    """A copy of conf/ with conf/plants/my_plant.yaml (cstr's model) of tag ``tag``."""
    conf = tmp_path / "conf"
    subprocess.run(["cp", "-r", str(conf_dir()), str(conf)], check=True)
    plant = yaml.safe_load((conf / "plants" / "cstr.yaml").read_text())
    (conf / "plants" / "my_plant.yaml").write_text(yaml.safe_dump({**plant, "tag": tag}))
    return conf


@pytest.mark.parametrize(
    ("tag", "message"),
    [
        (
            27,  # 25 free: a row no plant would train
            "the catalogue's tags leave tag 25 unused (a policy row no plant trains): the 26 "
            "files of conf/plants must have tags 0..25; give 'my_plant' (tag 27) tag 25",
        ),
        (
            24,  # f16_pitch's, a plant outside the set: the catalogue's tags are checked
            "conf/plants/f16_pitch.yaml and conf/plants/my_plant.yaml share tag 24; tags must "
            "be unique: give one of them the free tag 25",
        ),
    ],
)
def test_generate_command_with_a_new_plant_whose_tag_wastes_or_takes_a_row_writes_nothing(
    tmp_path, tag, message
):
    """``python -m generalist_control.generate`` with an added plant file: the tag is checked."""
    conf = _conf_with_plant(tmp_path, tag)
    out = tmp_path / "demos"
    cmd = [sys.executable, "-m", "generalist_control.generate", "systems=paper"]
    cmd += ["+plants@systems.plants.my_plant=my_plant", "data.duration=1.0"]
    cmd += [f"paths.data_dir={out}", f"hydra.run.dir={tmp_path / 'hydra'}"]
    env = {**_env(), "GC_CONF_DIR": str(conf)}
    proc = run_command(cmd, cwd=REPO, env=env, timeout=300)
    assert proc.returncode != 0
    assert message in proc.stderr
    assert not out.exists()


def test_the_tag_count_is_the_catalogues_and_an_explicit_one_is_kept(tmp_path, monkeypatch):
    assert tag_count() == len(available_plants()) == 25
    assert tag_count(30) == 30
    with pytest.raises(ValueError, match=r"model\.plant\.n_tags must be an integer, got 25\.5"):
        tag_count(25.5)
    assert compose_cfg().model.plant.n_tags == 25  # ${gc.tag_count:}
    monkeypatch.setenv("GC_CONF_DIR", str(_conf_with_plant(tmp_path, 25)))
    assert tag_count() == 26 and catalogue_tags()["my_plant"] == 25
    cfg = compose_cfg("systems=paper")  # a set without it: the rows are the catalogue's
    assert cfg.model.plant.n_tags == 26
    assert read_training(as_dict(cfg)).model["plant"]["n_tags"] == 26  # the policy's file holds 26
    assert (
        read_training(as_dict(compose_cfg("model.plant.n_tags=40"))).model["plant"]["n_tags"] == 40
    )


def test_data_module_keeps_the_included_plants_with_the_same_split(tiny_data_dir):
    loader = config_section(LoaderSettings, "loader", batch_size=64)
    full = DemoDataModule(tiny_data_dir, 8, 3, loader)
    one = DemoDataModule(tiny_data_dir, 8, 3, loader, plants=["cstr"])
    full.setup()
    one.setup()
    assert one.tags == {"cstr": 10} and one.orders == {"cstr": 2}
    assert set(full.tags) == {"cstr", "hydraulic_actuator"}
    assert one.meta()["tags"] == {"cstr": 10}
    for name in ("train_set", "val_set"):
        kept, every = getattr(one, name).tensors, getattr(full, name).tensors
        assert set(kept["tag"].tolist()) == {10}
        cstr = every["tag"] == 10
        for k in kept:  # the plant kept has exactly the windows it has without include
            assert torch.equal(kept[k], every[k][cstr]), (name, k)


def test_data_module_without_plants_is_the_previous_split(tiny_data_dir, tiny_demos):
    dm = DemoDataModule(tiny_data_dir, 8, 3, config_section(LoaderSettings, "loader"), seed=3)
    dm.setup()
    windows = tiny_demos.windows(8, 3)
    is_val = split_by_trajectory(tiny_demos.plant, 0.1, 3)[windows.traj]
    for name, keep in (("train_set", ~is_val), ("val_set", is_val)):
        before = WindowTensors(windows, keep).tensors
        for k, v in getattr(dm, name).tensors.items():
            assert torch.equal(v, before[k]), (name, k)


def test_data_module_names_an_included_plant_the_data_lacks(tiny_data_dir):
    loader = config_section(LoaderSettings, "loader")
    dm = DemoDataModule(tiny_data_dir, 8, 3, loader, plants=["cstr", "unstable"])
    with pytest.raises(MissingPlantError, match=r"\(systems\) names \['unstable'\]") as e:
        dm.setup()
    assert f"paths.data_dir={tiny_data_dir}" in str(e.value)
    assert "systems.include=[cstr,hydraulic_actuator]" in str(e.value)


def test_training_on_a_set_the_data_lacks_is_refused_before_logging(tiny_data_dir, tmp_path):
    """systems=paper on data of other plants: refused, not trained on the data's plants."""
    cfg = _train_cfg(tiny_data_dir, tmp_path, "systems=paper", "~systems.include")
    with pytest.raises(MissingPlantError, match=r"the plant set \(systems\) names \["):
        train(cfg)
    assert not (tmp_path / "mlflow.db").exists()


def test_training_with_include_trains_on_those_plants_only(tiny_data_dir, tmp_path):
    """DAgger and the closed-loop check off: include alone selects the plants."""
    off = ["dagger=null", "closed_loop_val=null", "monitor=val/loss"]
    off.append("closed_loop.systems=[]")
    cfg = _train_cfg(tiny_data_dir, tmp_path, "systems.include=[cstr]", *off)
    metrics, objects = train(cfg)
    dm = objects["datamodule"]
    for windows in (dm.train_set, dm.val_set):
        assert set(windows.tensors["tag"].tolist()) == {10}
    _, meta = load_policy(objects["policy_path"])
    assert meta["tags"] == {"cstr": 10}
    assert "val/mse/cstr" in metrics and "val/mse/hydraulic_actuator" not in metrics


def test_training_refuses_an_include_outside_the_set_before_logging(tiny_data_dir, tmp_path):
    cfg = _train_cfg(tiny_data_dir, tmp_path, "systems=paper", "systems.include=[cstr,nope]")
    with pytest.raises(UnknownPlantError, match="unknown plant 'nope'"):
        train(cfg)
    assert not (tmp_path / "mlflow.db").exists()


@pytest.mark.parametrize(
    "name",
    [
        "config.yaml",
        "data/demos.yaml",
        "evaluation/default.yaml",
        "model/generalist.yaml",
        "report/default.yaml",
        "systems/all.yaml",
        "trainer/default.yaml",
    ],
)
def test_files_dvc_exp_run_edits_hold_no_interpolation(name):
    """`dvc exp run -S <file>:<key>=<value>` loads the file alone: a ${...} there fails it."""
    code = [line.split("#", 1)[0] for line in (conf_dir() / name).read_text().splitlines()]
    assert not [line for line in code if "${" in line], name


#: A refused config, in a process of its own: is Lightning loaded when the error comes?
_REFUSED = """
import sys
from hydra import compose, initialize_config_dir
from generalist_control.common.paths import conf_dir
from generalist_control import {stage}
with initialize_config_dir(str(conf_dir()), version_base="1.3"):
    cfg = compose("{config}", overrides={overrides!r})
try:
    {stage}.run(cfg)
except ValueError as e:
    print("refused:", e, "| lightning loaded:", "lightning" in sys.modules)
"""


@pytest.mark.parametrize(
    ("stage", "config", "override", "message"),
    [
        ("train", "config", "trainer.max_epochs=1.5", "trainer.max_epochs"),
        ("tune", "tune", "hparams_search.direction=sideways", "minimize or maximize"),
    ],
)
def test_a_refused_config_answers_before_lightning_loads(stage, config, override, message):
    """train.py and tune.py import their work (Lightning) only once the config is read."""
    code = _REFUSED.format(stage=stage, config=config, overrides=[override])
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "refused:" in proc.stdout and message in proc.stdout, proc.stdout
    assert proc.stdout.rstrip().endswith("lightning loaded: False"), proc.stdout
