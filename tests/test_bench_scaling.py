"""benchmarks/bench_scaling.py: the growth exponent, the plant sets, a smoke run's JSON.

Nothing here times anything: the smoke run only checks that the script runs and what its
JSON holds.
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
from dataclasses import replace
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from omegaconf import OmegaConf

from generalist_control.plants.catalog import load_plant
from helpers import compose_cfg, run_command

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "benchmarks" / "bench_scaling.py"


def _bench():
    spec = importlib.util.spec_from_file_location("bench_scaling", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up
    with mock.patch.dict(os.environ):  # it pins BLAS threads; keep them off other tests
        spec.loader.exec_module(module)
    return module


bench = _bench()


def test_growth_exponent_of_known_costs():
    assert bench.growth_exponent([1, 2, 4], [1, 4, 16]) == pytest.approx(2.0, abs=1e-12)
    assert bench.growth_exponent([25, 50, 100], [3.0, 6.0, 12.0]) == pytest.approx(1.0)
    assert bench.growth_exponent([25, 50, 100], [7.0, 7.0, 7.0]) == pytest.approx(0.0)
    n, cost = [25, 50, 100], [2.0, 5.0, 9.0]  # not a power law: the least-squares slope
    expected = np.polyfit(np.log(n), np.log(cost), 1)[0]
    assert bench.growth_exponent(n, cost) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(
    ("counts", "costs"),
    [([25], [1.0]), ([25, 25], [1.0, 2.0]), ([25, 50], [1.0, 0.0]), ([25, 50], [1.0, np.nan])],
)
def test_growth_exponent_undefined(counts, costs):
    assert bench.growth_exponent(counts, costs) is None


def test_plant_set_adds_distinct_variants_with_their_own_tags():
    catalogue = [replace(load_plant(name), tag=i) for i, name in enumerate(["cstr", "dc_servo"])]
    data = OmegaConf.to_container(compose_cfg("data.duration=2.0").data, resolve=True)
    five = bench.plant_set(catalogue, 5, data)
    assert [p.name for p in five] == [
        "cstr", "dc_servo", "cstr_v1", "dc_servo_v1", "cstr_v2",
    ]  # fmt: skip
    assert [p.tag for p in five] == list(range(5))
    assert five[:2] == catalogue
    for p in five[2:]:
        nominal = next(c for c in catalogue if p.name.startswith(c.name))
        assert p.order == nominal.order
        assert not np.allclose(p.A, nominal.A) or p.params != nominal.params
    assert not np.allclose(five[2].A, five[4].A)  # two variants of one plant differ
    three = bench.plant_set(catalogue, 3, data)  # a smaller set is the start of a larger one
    assert [p.name for p in three] == [p.name for p in five[:3]]
    np.testing.assert_array_equal(three[2].A, five[2].A)
    assert bench.plant_set(catalogue, 1, data) == catalogue[:1]


@pytest.mark.slow  # ~20 s on a loaded 2-core machine
def test_smoke_run_writes_the_json(tmp_path):
    out = tmp_path / "results" / "scaling.json"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "src"), str(REPO)])}
    proc = run_command(
        [sys.executable, str(SCRIPT), "--smoke", "--out", str(out)],
        cwd=tmp_path, env=env, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "growth exponent" in proc.stdout and f"wrote {out}" in proc.stdout
    result = json.loads(out.read_text())
    assert result["smoke"] is True and result["catalogue"] == 2
    assert [c["plants"] for c in result["counts"]] == [2, 4]
    assert [c["variants"] for c in result["counts"]] == [0, 2]
    for key in ("loadavg_start", "loadavg_end"):
        assert len(result[key]) == 3
    assert {"cpu", "cpu_count", "torch"} <= set(result["machine"])
    for c in result["counts"]:
        assert c["data"]["windows"] > c["data"]["train_windows"] > 0
        cpu = c["epoch"]["cpu"]
        assert cpu["threads"] == 1 and cpu["epoch_s_kind"] == "measured: whole epoch"
        assert cpu["timed_samples"] == c["data"]["train_windows"] and cpu["epoch_s"] > 0
        gpu = c["epoch"]["gpu"]
        assert gpu.get("available", True) is False or gpu["epoch_s"] > 0
        ev = c["evaluation"]
        assert ev["scenarios"] == 2 and ev["median_s"] > 0 and ev["gc_runs"] > 0
    assert result["counts"][1]["data"]["windows"] == 2 * result["counts"][0]["data"]["windows"]
    growth = result["growth"]
    assert set(growth) == {"data_s", "windows", "epoch_cpu_s", "epoch_gpu_s", "evaluation_s"}
    assert growth["windows"] == pytest.approx(1.0)
    assert all(isinstance(growth[k], float) for k in ("data_s", "epoch_cpu_s", "evaluation_s"))
    assert not list(out.parent.glob(".*tmp*"))  # written through a temporary file and a rename
