"""The ``generate_families`` stage: same seed same bytes, its manifest, its DVC stage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from generalist_control.data.demos import load_demos
from generalist_control.generate_families import run
from generalist_control.plants.families import plant_from_record
from generalist_control.simulation.family_draw import REASONS
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import simulate
from helpers import compose_cfg
from test_layout import MODULES, _closure

REPO = Path(__file__).resolve().parents[1]
#: A dozen plants, 4 s trajectories (the unit step must settle within them).
TINY = ("families.count=12", "data.duration=4.0", "families.checks.settle_fraction=1.0")


def _run(out: Path, *extra: str) -> dict:
    return run(compose_cfg(*TINY, f"families.data_dir={out}", *extra, config="generate_families"))


def test_same_seed_same_bytes_and_the_manifest_records_every_plant_and_refusal(tmp_path):
    first, second = _run(tmp_path / "a"), _run(tmp_path / "b")
    for name in ("trajectories.parquet", "manifest.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert first["content_hash"] == second["content_hash"]

    demos, manifest = load_demos(tmp_path / "a")  # the catalogue's format, checked on load
    family = manifest["plant_family"]
    counts, plants = family["counts"], family["plants"]
    assert counts["kept"] == len(plants) == 12 and family["seed"] == 1
    assert counts["candidates"] == counts["kept"] + sum(counts[r] for r in REASONS)
    assert len(family["rejected"]) == counts["candidates"] - 12 > 0
    for r in family["rejected"]:
        assert r["reason"] in REASONS and r["message"] and "index" in r and "poles" in r
    assert sorted(p["tag"] for p in plants.values()) == list(range(12))
    assert sorted(set(demos.plant.tolist())) == sorted(plants)
    assert set(demos.family.tolist()) == {"steps", "staircase"}  # two per plant
    assert len(demos.r) == 24 and sorted(set(demos.tag.tolist())) == list(range(12))
    for name in plants:  # the manifest holds each plant in full: its data replays bit for bit
        plant = plant_from_record(family, name, manifest["dt"])
        row = np.flatnonzero((demos.plant == name) & (demos.family == "steps"))
        assert plant.tag == demos.tag[row[0]] and plant.order == demos.order[row[0]]
        tr = simulate(plant, LQIController(plant), demos.r[row])
        assert np.array_equal(tr.y[:, :-1], demos.y[row])
        assert np.array_equal(tr.x[:, :-1], demos.x[row][:, :, : plant.order])
    assert manifest["config"]["families"]["generator"]["seed"] == 1

    other = _run(tmp_path / "c", "families.generator.seed=2")
    assert other["content_hash"] != first["content_hash"]
    assert all(name.startswith("default_s2_") for name in other["plant_family"]["plants"])
    assert not set(other["plant_family"]["plants"]) & set(plants)


def test_the_dvc_stage_depends_on_the_code_it_imports_and_writes_the_familys_folder():
    spec = yaml.safe_load((REPO / "beyond" / "dvc.yaml").read_text())["stages"]
    stage = spec["generate_families"]
    deps = [REPO / d for d in stage["deps"]]
    missing = [
        str(MODULES[m].relative_to(REPO))
        for m in sorted(_closure("generalist_control.generate_families"))
        if not any(MODULES[m] == d or d in MODULES[m].parents for d in deps)
    ]
    assert not missing
    assert "python -m generalist_control.generate_families" in stage["cmd"]
    data_dir = compose_cfg(config="generate_families").families.data_dir
    assert stage["outs"] == [data_dir] and data_dir == "data/families/default"
