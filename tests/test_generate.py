"""The data stage: grid, counts, manifest, determinism, atomic writes and input errors."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from generalist_control.common.sections import as_dict
from generalist_control.data import demos as demos_mod
from generalist_control.data.demos import MissingDataError, load_demos
from generalist_control.data.generation import DataConfigError, amplitude_grid
from generalist_control.generate import run
from generalist_control.plants.catalog import UnknownPlantError, plants_from_config
from generalist_control.plants.definition import PlantConfigError
from helpers import compose_cfg

PAPER_WINDOWS = 314_630


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    """The default data stage (every plant of the default set), written once for this module."""
    out = tmp_path_factory.mktemp("gen") / "demos"
    manifest = run(compose_cfg(f"paths.data_dir={out}"))
    return out, manifest


def test_default_grid_is_non_uniform_and_bounded():
    grid = amplitude_grid(compose_cfg().data.amplitudes)
    assert grid.min() == -20 and grid.max() == 20 and 0 not in grid
    np.testing.assert_allclose(grid, -grid[::-1])
    gaps = set(np.round(np.diff(grid[grid > 0]), 6))
    assert {0.2, 1.0, 5.0} <= gaps


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    """The paper's data stage (``experiment=paper``: steps from rest only)."""
    out = tmp_path_factory.mktemp("gen") / "paper"
    manifest = run(compose_cfg("experiment=paper", f"paths.data_dir={out}"))
    return out, manifest


def test_paper_counts_match_the_paper(paper):
    out, manifest = paper
    n = len(
        plants_from_config(as_dict(compose_cfg().systems))
    )  # the paper's 25, and any plant added
    the_papers = [m for m in manifest["plants"].values() if m["tag"] < 25]
    windows = sum(m["n_demonstrations"] for m in the_papers)
    assert len(the_papers) == 25 and abs(windows - PAPER_WINDOWS) / PAPER_WINDOWS < 0.01
    assert manifest["n_demonstrations"] == n * 64 * (200 - 3 + 1)
    assert set(manifest["families"]) == {"steps"}
    assert len(manifest["plants"]) == n
    assert {m["order"] for m in the_papers} == {2, 3, 4}
    assert sorted(m["tag"] for m in manifest["plants"].values()) == list(range(n))
    assert (
        sum(m["n_demonstrations"] for m in manifest["plants"].values())
        == manifest["n_demonstrations"]
    )
    assert manifest["history"] == 8 and manifest["horizon"] == 3 and manifest["dt"] == 0.05
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk["content_hash"] == manifest["content_hash"]
    assert on_disk["config"]["data"]["amplitudes"]["limit"] == 20.0


def test_default_families_are_counted_per_family(full, paper):
    """Ours: the paper's steps plus every family of conf/data, counted in the manifest."""
    out, manifest = full
    cfg = compose_cfg()
    per_traj = 200 - 3 + 1
    n = len(plants_from_config(as_dict(cfg.systems)))
    expected = {"steps": n * 64}
    expected.update({k: n * int(v["count"]) for k, v in cfg.data.families.items()})
    got = {k: v["n_trajectories"] for k, v in manifest["families"].items()}
    assert got == expected
    assert all(
        v["n_demonstrations"] == v["n_trajectories"] * per_traj
        for v in manifest["families"].values()
    )
    assert manifest["n_demonstrations"] == sum(expected.values()) * per_traj
    # the step family is the paper's dataset, trajectory for trajectory
    demos, _ = load_demos(out)
    steps, _ = load_demos(paper[0])
    keep = demos.family == "steps"
    np.testing.assert_array_equal(demos.x[keep], steps.x)
    np.testing.assert_array_equal(demos.u[keep], steps.u)
    # random initial states: half of the staircases start away from rest, all holds do
    moving = np.abs(demos.x[:, 0]).max(axis=1) > 0
    assert moving[demos.family == "hold"].all()
    assert moving[demos.family == "staircase"].mean() == pytest.approx(0.5)
    assert not moving[keep].any()


def test_loaded_windows_match_manifest_and_expert(full):
    out, manifest = full
    demos, _ = load_demos(out)
    w = demos.windows(manifest["history"], manifest["horizon"])
    assert len(w) == manifest["n_demonstrations"]
    for name, m in manifest["plants"].items():
        assert (
            np.sum(np.isin(w.traj, np.flatnonzero(demos.plant == name))) == m["n_demonstrations"]
        )
        assert np.all(demos.order[demos.plant == name] == m["order"])
    assert np.all(w.state[w.mask == 0] == 0)
    # every LQI step demonstration settles to its step by the end of the horizon
    steps = demos.family == "steps"
    rel = np.abs(demos.y[steps, -1] - demos.r[steps, -1]) / np.abs(demos.r[steps, -1])
    assert rel.max() < 0.02, demos.plant[steps][rel.argmax()]


def test_same_config_same_hash_byte_for_byte(full, tmp_path):
    out, manifest = full
    again = run(compose_cfg(f"paths.data_dir={tmp_path / 'demos'}"))
    assert again["content_hash"] == manifest["content_hash"]
    for name in ("trajectories.parquet", "manifest.json"):
        assert (tmp_path / "demos" / name).read_bytes() == (out / name).read_bytes()


def test_changed_grid_changes_hash(tmp_path):
    base = ["systems=paper", "data.duration=2.0"]
    a = run(compose_cfg(*base, f"paths.data_dir={tmp_path / 'a'}"))
    b = run(
        compose_cfg(
            *base, "data.amplitudes.segments.0.step=0.4", f"paths.data_dir={tmp_path / 'b'}"
        )
    )
    assert a["content_hash"] != b["content_hash"]
    assert b["n_trajectories"] < a["n_trajectories"]


@pytest.mark.parametrize(
    ("overrides", "error", "match"),
    [
        (["systems.include=[cstr,nope]"], UnknownPlantError, "unknown plant 'nope'; known"),
        (["systems.plants.cstr.lqi.R=-1"], PlantConfigError, "plant 'cstr'.*lqi.R"),
        (["systems.plants.cstr.lqi.Q=[1,1]"], PlantConfigError, "plant 'cstr'.*lqi.Q.*shape"),
        (["systems.plants.cstr.C=[[0,1]]"], PlantConfigError, "transmission zero at s = 0"),
        (["data.amplitudes.segments.2.stop=25"], DataConfigError, r"segments\[2\].stop = 25"),
        (["data.amplitudes.segments.0.step=0"], DataConfigError, r"segments\[0\].step"),
        (["systems.plants.cstr.dt=0.1"], DataConfigError, "share a sample time"),
    ],
)
def test_bad_input_fails_before_writing(tmp_path, overrides, error, match):
    out = tmp_path / "demos"
    with pytest.raises(error, match=match):
        run(compose_cfg("systems=paper", f"paths.data_dir={out}", *overrides))
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_interrupted_write_keeps_previous_dataset(tmp_path, monkeypatch):
    out = tmp_path / "demos"
    cfg = compose_cfg("systems=paper", "data.duration=1.0", f"paths.data_dir={out}")
    first = run(cfg)

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(demos_mod.pq, "write_table", boom)
    with pytest.raises(KeyboardInterrupt):
        run(compose_cfg("systems=paper", "data.duration=2.0", f"paths.data_dir={out}"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demos"]
    assert json.loads((out / "manifest.json").read_text())["content_hash"] == first["content_hash"]


def test_missing_data_error_gives_the_command(tmp_path):
    with pytest.raises(MissingDataError, match="python -m generalist_control.generate"):
        load_demos(tmp_path / "nowhere")


def test_sets_compose_the_documented_plants():
    def names(s):
        return [p.name for p in plants_from_config(as_dict(compose_cfg(f"systems={s}").systems))]

    assert sorted(names("paper")) == sorted(
        [
            "unstable",
            "cstr",
            "hydraulic_actuator",
            "auv_yaw",
            "boeing747",
            "two_mass_spring",
            "crazyflie_altitude",
        ]
    )
    assert sorted(names("ablation")) == sorted(
        ["double_integrator", "crazyflie_altitude", "cstr", "mass_spring_damper", "hvac_two_zone"]
    )


def test_cli_entry_point_quiet_when_not_a_tty(tmp_path):
    out = tmp_path / "demos"
    env = {**os.environ, "HYDRA_FULL_ERROR": "1"}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "generalist_control.generate",
            "systems=paper",
            f"paths.data_dir={out}",
            f"hydra.run.dir={tmp_path / 'hydra'}",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "generate:" not in proc.stderr and "it/s" not in proc.stderr  # no progress bar
    n_families = sum(int(v["count"]) for v in compose_cfg().data.families.values())
    assert json.loads((out / "manifest.json").read_text())["n_trajectories"] == 7 * (
        64 + n_families
    )
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "generalist_control.generate",
            "systems=nope",
            f"paths.data_dir={out}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert bad.returncode != 0 and "Could not find 'systems/nope'" in bad.stderr
    assert "paper" in bad.stderr  # Hydra lists the available sets
    assert Path(out).exists()  # the previous dataset is untouched
