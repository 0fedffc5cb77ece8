"""Config values are taken as typed, never rounded or ignored (issue 10, items 7 and 8).

* integer keys of ``model``, ``experts`` and ``loader`` refuse non-integers (schema at
  composition, strict checks at run time), before anything is logged or trained;
* ``generate`` refuses a plant tag outside ``0..model.n_tags-1`` before writing;
* ``systems.include`` selects the training plants even with DAgger and the closed-loop
  check off.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from generalist_control.common.paths import conf_dir
from generalist_control.common.schema import ModelSchema, require_fraction, require_int
from generalist_control.generate import run as generate_run
from generalist_control.model.network import MODEL_DEFAULTS, network_config
from generalist_control.model.policy import load_policy
from generalist_control.plants.catalog import UnknownPlantError
from generalist_control.plants.plant import PlantConfigError
from generalist_control.training.datamodule import (
    DemoDataModule,
    MissingPlantError,
    WindowTensors,
    split_by_trajectory,
)
from generalist_control.training.fit import train
from helpers import compose_cfg, tiny_train_overrides

REPO = Path(__file__).resolve().parents[1]
#: Network keys set in the ``model`` group (the others come from ``experts`` and ``data``;
#: ``unknown_tag`` follows from ``model.tag_dropout``, ``identity_head`` from
#: ``model.identity_loss``).
MODEL_GROUP_KEYS = set(MODEL_DEFAULTS) - {
    "experts",
    "state_dim",
    "history",
    "horizon",
    "unknown_tag",
    "identity_head",
}
#: Boolean keys of the ``model`` group that set training, not the network.
TRAINING_SWITCHES = {"identity_noise_clean_fit"}


def _env() -> dict[str, str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    return env


def _train_cfg(data_dir: Path, out: Path, *extra: str):
    uri = f"sqlite:///{out / 'mlflow.db'}"
    return compose_cfg(*tiny_train_overrides(data_dir, out, uri, "logger.log_model=false", *extra))


# ------------------------------------------------------------------ item 7: integer sizes
@pytest.mark.parametrize(
    "override",
    [
        "model.hidden=32.9",
        "model.hidden=32.0",
        "model.hidden='32.5'",
        "model.hidden=true",
        "model.heads=2.5",
        "model.stride=1.5",
        "model.n_tags=25.5",
        "model.linear_samples=0.5",
    ],
)
def test_a_non_integer_model_size_fails_at_composition(override):
    key, value = override.split("=")
    with pytest.raises(ConfigCompositionException) as err:
        compose_cfg(override)
    cause = str(err.value.__cause__)
    assert f"full_key: {key}" in cause and "could not be converted to Integer" in cause
    assert value.strip("'").lower() in cause.lower()


def test_the_schema_types_exactly_the_model_group():
    names = {f.name for f in dataclasses.fields(ModelSchema)}
    for path in sorted((conf_dir() / "model").glob("*.yaml")):
        spec = yaml.safe_load(path.read_text())
        assert {"optional /gc_schema@_here_": "model"} in spec["defaults"], path
        assert set(spec) - {"defaults"} == names, path
    sizes = {f.name for f in dataclasses.fields(ModelSchema) if f.type in ("int", "bool")}
    assert sizes == MODEL_GROUP_KEYS | TRAINING_SWITCHES
    cfg = compose_cfg()
    assert OmegaConf.get_type(cfg.model) is ModelSchema
    assert cfg.model.hidden == 32 and cfg.model.integral is True


def test_a_composition_without_the_package_still_works(tmp_path):
    """DVC's Hydra composes conf/ without importing the package: the schema is optional."""
    code = (
        "from hydra import compose, initialize_config_dir\n"
        f"with initialize_config_dir({str(conf_dir())!r}, version_base='1.3'):\n"
        "    cfg = compose('config', overrides=['model.hidden=16', 'experiment=paper'])\n"
        "print(cfg.model.hidden, cfg.model.integral)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["16", "False"]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"hidden": 32.9}, "model.hidden must be an integer, got 32.9 (float)"),
        ({"hidden": 32.0}, "model.hidden must be an integer, got 32.0 (float)"),
        ({"hidden": "32"}, "model.hidden must be an integer, got '32' (str)"),
        ({"hidden": True}, "model.hidden must be an integer, got True (bool)"),
        ({"heads": 2.5}, "model.heads must be an integer, got 2.5 (float)"),
        ({"stride": 1.5}, "model.stride must be an integer, got 1.5 (float)"),
        ({"experts": 2.5}, "experts must be an integer, got 2.5 (float)"),
        ({"n_tags": 25.5}, "model.n_tags must be an integer, got 25.5 (float)"),
        ({"linear_samples": 1.5}, "model.linear_samples must be an integer, got 1.5"),
        ({"history": 8.5}, "data.history must be an integer, got 8.5 (float)"),
        ({"integral": 0.5}, "model.integral must be 0 or 1 (false/true), got 0.5 (float)"),
        ({"experts": 0}, "experts must be a positive integer, got 0"),
    ],
)
def test_network_config_refuses_what_it_would_have_rounded(kwargs, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        network_config(**kwargs)


def test_network_config_takes_integers_of_any_kind_and_boolean_switches():
    cfg = network_config(hidden=np.int64(16), experts=np.int32(2), integral=True)
    assert cfg["hidden"] == 16 and cfg["experts"] == 2 and cfg["integral"] == 1
    assert all(type(v) is int for v in cfg.values())
    assert require_int("x", 0, minimum=0) == 0
    assert require_fraction("loader.val_fraction", 0) == 0.0
    with pytest.raises(ValueError, match=r"loader.val_fraction must lie in \[0, 1\), got 1.0"):
        require_fraction("loader.val_fraction", 1.0)
    with pytest.raises(ValueError, match=r"must be a number in \[0, 1\), got True \(bool\)"):
        require_fraction("loader.val_fraction", True)


def test_train_py_with_a_fractional_size_fails_and_logs_nothing(tiny_data_dir, tmp_path):
    """The issue's command, ``python train.py model.hidden=32.9``, on tiny data."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    overrides = tiny_train_overrides(tiny_data_dir, tmp_path, uri)
    cmd = [sys.executable, "train.py", "model.hidden=32.9", *overrides]
    cmd.append(f"hydra.run.dir={tmp_path / 'hydra'}")
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=_env(), timeout=300)
    assert proc.returncode != 0
    assert "Value '32.9' of type 'float' could not be converted to Integer" in proc.stderr
    assert "full_key: model.hidden" in proc.stderr
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "models").exists()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("experts=2.5", r"experts must be an integer, got 2\.5 \(float\)"),
        ("loader.batch_size=10.5", r"loader\.batch_size must be an integer, got 10\.5 \(float\)"),
        ("loader.val_batch_size=64.0", r"loader\.val_batch_size must be an integer, got 64\.0"),
        ("loader.val_fraction=1.5", r"loader\.val_fraction must lie in \[0, 1\), got 1\.5"),
    ],
)
def test_train_refuses_a_fractional_size_before_logging(
    tiny_data_dir, tmp_path, override, message
):
    cfg = _train_cfg(tiny_data_dir, tmp_path, override)
    with pytest.raises(ValueError, match=message):
        train(cfg)
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "models").exists()


def test_train_refuses_a_fractional_model_size_composed_without_the_schema(
    tiny_data_dir, tmp_path
):
    """Whatever composed the config (no schema: a plain copy), the run-time check holds."""
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
            r"plant 'cstr' \(tag 25\) is outside the policy's tags 0\.\.24 \(model\.n_tags=25\)"
            r"; raise model\.n_tags to at least 26 .* or give it a free tag in 0\.\.24 "
            r"\(conf/plants/<name>\.yaml",
        ),
        (["systems.plants.cstr.tag=-1"], r"plant 'cstr' \(tag -1\) is outside .* 0\.\.24"),
        (
            ["model.n_tags=10", "systems.include=[cstr,unstable]"],
            r"plants 'cstr' \(tag 10\), 'unstable' \(tag 11\) are outside the policy's tags "
            r"0\.\.9 \(model\.n_tags=10\); raise model\.n_tags to at least 12",
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


def test_generate_command_with_a_new_plant_past_n_tags_writes_nothing(tmp_path):
    """``python -m generalist_control.generate`` with an added plant file whose tag is 25."""
    conf = tmp_path / "conf"
    subprocess.run(["cp", "-r", str(conf_dir()), str(conf)], check=True)
    plant = yaml.safe_load((conf / "plants" / "cstr.yaml").read_text())
    (conf / "plants" / "my_plant.yaml").write_text(yaml.safe_dump({**plant, "tag": 25}))
    out = tmp_path / "demos"
    cmd = [sys.executable, "-m", "generalist_control.generate", "systems=paper"]
    cmd += ["+plants@systems.plants.my_plant=my_plant", "data.duration=1.0"]
    cmd += [f"paths.data_dir={out}", f"hydra.run.dir={tmp_path / 'hydra'}"]
    env = {**_env(), "GC_CONF_DIR": str(conf)}
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode != 0
    assert "plant 'my_plant' (tag 25) is outside the policy's tags 0..24" in proc.stderr
    assert "raise model.n_tags to at least 26" in proc.stderr
    assert not out.exists()


def test_data_module_keeps_the_included_plants_with_the_same_split(tiny_data_dir):
    full = DemoDataModule(tiny_data_dir, 8, 3, batch_size=64)
    one = DemoDataModule(tiny_data_dir, 8, 3, batch_size=64, plants=["cstr"])
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
    dm = DemoDataModule(tiny_data_dir, 8, 3, seed=3)
    dm.setup()
    windows = tiny_demos.windows(8, 3)
    is_val = split_by_trajectory(tiny_demos.plant, 0.1, 3)[windows.traj]
    for name, keep in (("train_set", ~is_val), ("val_set", is_val)):
        before = WindowTensors(windows, keep).tensors
        for k, v in getattr(dm, name).tensors.items():
            assert torch.equal(v, before[k]), (name, k)


def test_data_module_names_an_included_plant_the_data_lacks(tiny_data_dir):
    dm = DemoDataModule(tiny_data_dir, 8, 3, plants=["cstr", "unstable"])
    with pytest.raises(MissingPlantError, match=r"systems\.include names \['unstable'\]") as e:
        dm.setup()
    assert (
        "python -m generalist_control.generate "
        f"systems.include=[cstr,hydraulic_actuator,unstable] paths.data_dir={tiny_data_dir}"
    ) in str(e.value)


def test_training_with_include_trains_on_those_plants_only(tiny_data_dir, tmp_path):
    """DAgger and the closed-loop check off: include alone selects the plants."""
    off = ["dagger.enabled=false", "closed_loop_val.enabled=false", "monitor=val/loss"]
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
