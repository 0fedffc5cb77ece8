"""Plant variants (issue 13, part 2): ranges, rejection, the data switch, the evaluation."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import control
import mlflow
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from generalist_control import evaluate as evaluate_stage
from generalist_control import generate as generate_stage
from generalist_control.data.demos import content_hash, load_demos, write_demos
from generalist_control.data.generation import build_manifest, generate_demos
from generalist_control.evaluation.variant_eval import (
    TrainingDraws,
    check_disjoint,
    evaluate_variants,
)
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.config import plant_from_config
from generalist_control.plants.definition import PlantConfigError
from generalist_control.plants.variants import (
    VariantError,
    make_variant,
    parameter_ranges,
)
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import simulate
from generalist_control.simulation.variant_sampling import (
    Variant,
    VariantDraw,
    check_class,
    check_variant,
    sample_variants,
)
from helpers import TINY_DATA, compose_cfg, tiny_train_overrides, train
from test_evaluate import LQIRuntime

TINY = TINY_DATA


def _fast_plant(a: float = 20.0):
    """First-order plant with an unstable pole at ``a``: near the limit of the 0.05 s sample."""
    cfg = {
        "tag": 0, "description": "d", "source": "s", "dt": 0.05,
        "states": [{"name": "x", "unit": "-"}], "input": {"name": "u", "unit": "-"},
        "output": {"name": "y", "unit": "-"}, "A": [[a]], "B": [[1.0]], "C": [[1.0]],
        "lqi": {"Q": [1.0, 1.0], "R": 1.0},
    }  # fmt: skip
    return plant_from_config("fast", cfg)


def test_perturbation_is_within_range_reproducible_and_keeps_structure():
    plant = load_plant("hydraulic_actuator")  # A[0,1] = 1 kinematic, zeros structural
    a = sample_variants(plant, 4, seed=5, default_range=0.25, steps=40)
    b = sample_variants(plant, 4, seed=5, default_range=0.25, steps=40)
    c = sample_variants(plant, 4, seed=6, default_range=0.25, steps=40)
    assert [v.factors for v in a.kept] == [v.factors for v in b.kept]
    assert [v.factors for v in a.kept] != [v.factors for v in c.kept]
    for v in a.kept:
        ratio_a = np.divide(v.plant.A, plant.A, out=np.ones_like(plant.A), where=plant.A != 0)
        ratio_b = np.divide(v.plant.B, plant.B, out=np.ones_like(plant.B), where=plant.B != 0)
        assert np.all(np.abs(np.concatenate([ratio_a.ravel(), ratio_b.ravel()]) - 1) <= 0.25)
        assert np.all(v.plant.A[plant.A == 0] == 0) and v.plant.A[0, 1] == 1.0
        assert ratio_a[1, 0] == pytest.approx(v.factors["A[1,0]"], rel=1e-15)
        assert not np.allclose(ratio_a, 1.0)
        assert (v.plant.name, v.plant.tag) == (plant.name, plant.tag)
    assert parameter_ranges(load_plant("coupled_tanks"))["A[1,0]"] == 0.25  # its 'include'


def test_nonlinear_variant_re_solves_u_op_at_the_nominal_state():
    plant = load_plant("two_tank")
    draw = sample_variants(plant, 3, seed=1, default_range=0.25, steps=40)
    assert set(draw.kept[0].factors) == {"A1", "A2"}  # a1, a2 and g are fixed by its file
    v = make_variant(plant, {"A1": 1.2, "A2": 0.8, "a1": 1.1, "a2": 1.1})  # a1 = a2 still
    # Torricelli: the inflow q = a2 sqrt(2 g h2) holds h2 = 50 cm
    assert v.u_op == pytest.approx(1.65 * np.sqrt(2 * 981.0 * 50.0), rel=1e-9)
    assert v.u_op != pytest.approx(plant.u_op)
    assert v.A[1, 1] == pytest.approx(plant.A[1, 1] * 1.1 / 0.8, rel=1e-6)  # -a2/(A2 ...)
    with pytest.raises(VariantError, match="no equilibrium at the nominal x_op"):
        make_variant(plant, {"a1": 1.1})  # a1 != a2: equal levels cannot be held


def test_unfit_variants_are_rejected_with_the_reason_and_redrawn():
    with pytest.raises(VariantError, match="LQI design refused it.*cstr"):
        check_variant(make_variant(load_plant("cstr"), {"B[1]": 0.0}), (1.0,), 40)
    plant = _fast_plant()
    draw = sample_variants(plant, 4, seed=0, default_range=0.25, steps=40)
    assert len(draw.kept) == 4 and len(draw.rejected) >= 1
    assert all("sampled at dt = 0.05 s is unstable" in r["reason"] for r in draw.rejected)
    # a faster unstable pole is what breaks the sampled loop: every reject is faster
    worst_kept = max(v.factors["A[0,0]"] for v in draw.kept)
    assert min(r["factors"]["A[0,0]"] for r in draw.rejected) > worst_kept
    with pytest.raises(VariantError, match="only 0 of 4 variants.*Narrow its range"):
        sample_variants(_fast_plant(30.0), 4, seed=0, default_range=0.25, steps=40)


def _linear_plant(A, B, C):
    """A linear plant from its matrices, LQI weights of ones."""
    n = len(A)
    cfg = {
        "tag": 0, "description": "d", "source": "s", "dt": 0.05,
        "states": [{"name": f"x{i}", "unit": "-"} for i in range(n)],
        "input": {"name": "u", "unit": "-"}, "output": {"name": "y", "unit": "-"},
        "A": A, "B": B, "C": C, "lqi": {"Q": [1.0] * (n + 1), "R": 1.0},
    }  # fmt: skip
    return plant_from_config("lin", cfg)


def test_a_variant_must_keep_the_nominal_plants_class():
    """As many right-half-plane poles and zeros as the nominal plant, else refused."""
    # stable 2x2 (det 0.16 - 0.15 > 0, trace < 0): A[0,0] x0.75 makes det < 0, one pole > 0
    stable = _linear_plant([[-0.1, 0.5], [0.3, -1.6]], [[1.0], [0.0]], [[1.0, 0.0]])
    check_class(make_variant(stable, {"A[0,0]": 1.05}), stable)  # det 0.018 > 0: kept
    unstable = make_variant(stable, {"A[0,0]": 0.75})
    pole = max(np.linalg.eigvals(unstable.A).real)  # closed form: det -0.03, one root > 0
    assert pole > 0
    with pytest.raises(
        VariantError, match=re.escape(f"poles in the right half-plane (rightmost at {pole:+.4g})")
    ):
        check_class(unstable, stable)
    # C = [1, 0]: the zero is at a22 - a12 b2 / b1 = -1 + 0.9 = -0.1; B[1] x1.2 moves it to +0.08
    minimum = _linear_plant([[-2.0, -1.0], [1.0, -1.0]], [[1.0], [0.9]], [[1.0, 0.0]])
    check_class(make_variant(minimum, {"B[1]": 1.1}), minimum)  # zero at -0.01: kept
    with pytest.raises(VariantError, match=r"1 open-loop zeros .*\(rightmost at \+0\.08\)"):
        check_class(make_variant(minimum, {"B[1]": 1.2}), minimum)
    # hvac_two_zone's rows are heat balances: this draw (an evaluation variant before the
    # rule) has an unstable pole and a DC gain of the other sign; it is refused by the sampler
    hvac = load_plant("hvac_two_zone")
    factors = {"A[0,0]": 0.873713, "A[0,1]": 1.120397, "A[0,2]": 1.219406, "A[1,0]": 0.794282,
               "A[1,1]": 1.093401, "A[2,0]": 0.973756, "A[2,2]": 0.776620, "A[2,3]": 1.169105,
               "A[3,2]": 0.991258, "A[3,3]": 1.204047, "B[0]": 0.785979}  # fmt: skip
    bad = make_variant(hvac, factors)
    dc = -(bad.C.reshape(1, -1) @ np.linalg.solve(bad.A, bad.B.reshape(-1, 1))).item()
    assert max(np.linalg.eigvals(bad.A).real) > 0 and dc < 0
    with pytest.raises(VariantError, match="changes the plant's class: 1 open-loop poles"):
        check_variant(bad, (1.0,), 40, hvac)
    check_variant(bad, (), 40)  # without its nominal plant, no class check: LQI accepts it
    draw = sample_variants(hvac, 8, seed=3002, default_range=0.25, steps=40)
    assert any("changes the plant's class" in r["reason"] for r in draw.rejected)
    for v in draw.kept:
        assert max(np.linalg.eigvals(v.plant.A).real) < 0


def test_plant_files_variants_block_is_validated():
    cfg = {
        "tag": 0, "description": "d", "source": "s", "dt": 0.05,
        "states": [{"name": "x", "unit": "-"}], "input": {"name": "u", "unit": "-"},
        "output": {"name": "y", "unit": "-"}, "A": [[-1.0]], "B": [[1.0]], "C": [[1.0]],
        "lqi": {"Q": [1.0, 1.0], "R": 1.0},
    }  # fmt: skip
    for block, msg in (
        ({"range": 1.5}, "variants.range"),
        ({"ranges": {"A[0,1]": 0.1}}, "names 'A\\[0,1\\]'"),
        ({"spread": 0.1}, "unknown keys"),
    ):
        with pytest.raises(PlantConfigError, match=msg):
            plant_from_config("p", {**cfg, "variants": block})
    p = plant_from_config("p", {**cfg, "variants": {"range": 0.1, "ranges": {"B[0]": 0.0}}})
    assert parameter_ranges(p) == {"A[0,0]": 0.1}


def _config(data):
    plants = {"fast": {"variants": {"range": 0.25}}, "two_tank": {"x": 1}}
    return {"systems": {"plants": plants}, "data": data}


def test_default_off_leaves_the_tiny_fixtures_bytes_and_hash_unchanged(tiny_data_dir):
    """The same data stage with a disabled ``data.variants`` block: the fixture's hash."""
    from conftest import TINY_PLANTS

    plants = [load_plant(n) for n in TINY_PLANTS]
    data = {**TINY_DATA, "variants": {"enabled": False, "count": 8, "seed": 1013}}
    demos = generate_demos(plants, data, progress=False)
    config = {"systems": {"name": "tiny", "include": list(TINY_PLANTS)}, "data": data}
    fixture, manifest = load_demos(tiny_data_dir)
    assert build_manifest(plants, demos, data, config)["content_hash"] == manifest["content_hash"]
    assert demos.variant is None and fixture.variant is None
    assert "variant" not in pq.read_schema(tiny_data_dir / "trajectories.parquet").names


def test_manifest_records_variants_and_the_rows_are_the_variants_runs(tmp_path):
    plants = [_fast_plant(), load_plant("two_tank")]
    base = generate_demos(plants, TINY, progress=False)
    off = {**TINY, "variants": {"enabled": False, "count": 3, "seed": 7}}
    demos_off = generate_demos(plants, off, progress=False)
    plain = {"fast": {}, "two_tank": {"x": 1}}
    m_base = build_manifest(plants, base, TINY, {"systems": {"plants": plain}, "data": TINY})
    m_off = build_manifest(plants, demos_off, off, _config(off))
    assert demos_off.variant is None
    assert m_off["content_hash"] == m_base["content_hash"] == content_hash(base, m_base["config"])
    assert "variants" not in m_off
    on = {
        **TINY,
        "variants": {"enabled": True, "count": 3, "seed": 7, "range": 0.25, "max_tries": 10},
    }
    demos = generate_demos(plants, on, progress=False)
    m_on = build_manifest(plants, demos, on, _config(on))
    assert m_on["content_hash"] != m_base["content_hash"]
    assert demos.r.shape == base.r.shape  # same size as the nominal set
    np.testing.assert_array_equal(demos.r, base.r)  # same references, other plants
    np.testing.assert_array_equal(demos.variant[:8], [0, 1, 2, 3, 0, 1, 2, 3])  # round robin
    rec = m_on["variants"]["fast"]
    assert len(rec["kept"]) == 3 and rec["rejected"] and "unstable" in rec["rejected"][0]["reason"]
    for v in rec["kept"]:
        assert v["parameters"]["A[0,0]"] == pytest.approx(20.0 * v["factors"]["A[0,0]"])
    # a row on variant 2 is that variant's LQI response (an independent single run)
    v2 = make_variant(plants[0], rec["kept"][1]["factors"])
    row = int(np.flatnonzero((demos.variant == 2) & (demos.plant == "fast"))[0])
    tr = simulate(v2, LQIController(v2), demos.r[row : row + 1])
    np.testing.assert_allclose(demos.y[row], tr.y[0, :-1], rtol=0, atol=1e-12)
    out = write_demos(tmp_path / "d", demos, m_on)
    assert "variant" in pq.read_schema(out / "trajectories.parquet").names
    loaded, _ = load_demos(out)
    np.testing.assert_array_equal(loaded.variant, demos.variant)


def _discrete_lqi_step(A, B, C, K, dt, steps):
    """Unit-step output: ZOH plant + forward-Euler integrator, by python-control."""
    sysd = control.c2d(control.ss(A, B, C, 0), dt, method="zoh")
    Ad, Bd = np.asarray(sysd.A), np.asarray(sysd.B)
    Kx, Ki = K[:, :-1], K[:, -1:]
    Acl = np.block([[Ad - Bd @ Kx, -Bd @ Ki], [-dt * C, np.ones((1, 1))]])
    Bcl = np.vstack([np.zeros((A.shape[0], 1)), [[dt]]])
    cl = control.ss(Acl, Bcl, np.hstack([C, [[0.0]]]), 0, dt)
    t = np.arange(steps) * dt
    return t, control.forced_response(cl, t, np.ones(steps)).outputs


def _discrete_lqi_ise(A, B, C, K, dt, steps):
    """ISE of a unit step: ZOH plant + forward-Euler integrator, by python-control."""
    t, y = _discrete_lqi_step(A, B, C, K, dt, steps)
    return float(np.trapezoid((1.0 - y) ** 2, t))


def test_lqi_nominal_and_oracle_match_python_control_on_a_hand_case():
    plant = load_plant("cstr")
    factors = {"A[1,0]": 0.8, "B[1]": 1.3}
    draw = VariantDraw(plant, [Variant(1, make_variant(plant, factors), factors)])
    scen = {"step": {"kind": "step", "amplitude": 1.0, "duration": 6.0}}
    df = evaluate_variants(LQIRuntime(["cstr"]), {"cstr": draw}, scen)
    assert list(df.columns) == [
        "system", "variant", "scenario", "controller", "run", "metric", "value"
    ]  # fmt: skip
    ise = df[df.metric == "ISE"].set_index("controller")["value"]
    A_var, B_var, C, k_nom, k_var = _cstr_hand_case()
    assert ise["LQI"] == pytest.approx(_discrete_lqi_ise(A_var, B_var, C, k_var, 0.05, 120))
    assert ise["LQI-nominal"] == pytest.approx(
        _discrete_lqi_ise(A_var, B_var, C, k_nom, 0.05, 120)
    )
    assert ise["LQI"] != pytest.approx(ise["LQI-nominal"])
    assert ise["GC"] == ise["LQI-nominal"]  # this "policy" is the nominal law


def test_evaluation_variants_must_differ_from_the_training_ones(tmp_path):
    plant = load_plant("cstr")
    data = TrainingDraws(tmp_path, data_seed=7, data_range=0.25, data_count=3, data_tries=10,
                         dagger_seeds=range(0), dagger_fresh=0)  # fmt: skip
    same = sample_variants(plant, 3, seed=7, default_range=0.25, steps=40)
    with pytest.raises(ValueError, match="equals a training variant"):
        check_disjoint({"cstr": same}, [plant], data, seed=8)
    with pytest.raises(ValueError, match="is data.variants.seed"):
        check_disjoint({"cstr": same}, [plant], data, seed=7)
    other = sample_variants(plant, 3, seed=8, default_range=0.25, steps=40)
    got = check_disjoint({"cstr": other}, [plant], data, seed=8)
    assert got["checked_against"].startswith("seed stream") and got["min_factor_distance"] > 0
    # DAgger's fresh variants (seeds 11, 12: one per round) count as training variants too
    dagger = replace(data, dagger_seeds=range(11, 13), dagger_fresh=2)
    fresh = sample_variants(plant, 2, seed=12, default_range=0.25, steps=40)  # round 1's
    with pytest.raises(ValueError, match=r"equals a training variant \(.*DAgger's fresh"):
        check_disjoint({"cstr": fresh}, [plant], dagger, 8)
    with pytest.raises(ValueError, match="one of DAgger's fresh-variant seeds"):
        check_disjoint({"cstr": other}, [plant], dagger, 12)
    got = check_disjoint({"cstr": other}, [plant], dagger, 8)
    assert "DAgger's fresh variants (seeds 11..12)" in got["checked_against"]
    off = check_disjoint({"cstr": fresh}, [plant], data, 8)  # dagger: null
    assert "DAgger" not in off["checked_against"]


@pytest.mark.slow
def test_tiny_variants_chain_writes_the_reports(tmp_path, mlflow_uri):
    tiny = [
        "experiment=variants",
        "systems.include=[cstr,two_tank]",
        "data.duration=2.0",
        "data.amplitudes.segments=[{start:1.0,stop:4.0,step:1.0}]",
        "data.families=null",
        "data.variants.count=2",
        f"paths.data_dir={tmp_path / 'data'}",
    ]
    manifest = generate_stage.run(compose_cfg(*tiny))
    assert set(manifest["variants"]) == {"cstr", "two_tank"}
    over = tiny_train_overrides(
        tmp_path / "data", tmp_path, mlflow_uri, "logger.log_model=false", "model.hidden=8",
        "experts=2", "closed_loop.systems=[cstr]", "closed_loop.duration=2.0",
        # one DAgger round on the nominal plants, 1 data variant each and 1 fresh one
        "dagger.start_epoch=0", "dagger.every=1", "dagger.rounds=1",
        "dagger.sampler.duration=2.0", "dagger.sampler.variants.data=1",
        "dagger.sampler.variants.fresh=1", "closed_loop_val.duration=2.0",
        "systems.include=[cstr,two_tank]",
    )  # fmt: skip
    _, objects = train(compose_cfg(*tiny, *over))
    run = mlflow.MlflowClient(mlflow_uri).get_run(objects["run_id"]).data
    assert float(run.params["dagger.sampler.noise"]) == 0.05  # the recipe: noisy rollouts
    logged = run.metrics
    scored = {k for k in logged if k.startswith("val/closed_loop/")}
    assert scored == {f"val/closed_loop/{p}" for p in ("cstr", "two_tank")}
    assert logged["dagger/windows"] > 0
    (cb,) = [c for c in objects["trainer"].callbacks if type(c).__name__ == "DAggerCallback"]
    assert {k: len(v) for k, v in cb.sampler.fresh.items()} == {"cstr": 1, "two_tank": 1}
    # per plant and round: the nominal version, 1 data variant in turn, 1 fresh variant
    assert [p.name for p in cb.sampler.round_plants(0)].count("cstr") == 3
    reports = tmp_path / "reports"
    ev = [
        *tiny, f"policy={objects['policy_path']}", f"paths.reports_dir={reports}",
        f"logger.tracking_uri={mlflow_uri}", f"logger.experiment_name={tmp_path.name}",
        "evaluation.scenarios.step.duration=3.0", "evaluation.variants.count=5",
        "evaluation.backend=torch", "evaluation.variants.validation.count=5",
        "dagger.rounds=1",  # the training's: its fresh variants are checked against
    ]  # fmt: skip
    cfg, clash = compose_cfg(*ev), compose_cfg(*ev, "evaluation.variants.validation.seed=2027")
    with pytest.raises(ValueError, match="validation.seed = 2027 is the test variants' seed"):
        evaluate_stage.run(clash)
    assert not reports.exists()  # refused before any work
    summary = evaluate_stage.run(cfg)
    df = pd.read_csv(reports / "metrics.csv")
    assert list(df.columns) == [
        "system", "variant", "scenario", "controller", "run", "metric", "value"
    ]  # fmt: skip
    assert set(df.controller) == {"GC", "LQI", "LQI-nominal"}
    assert sorted(df.variant.unique()) == [1, 2, 3, 4, 5]
    assert {"ISE", "ITAE", "diverged"} <= set(df.metric)
    saved = json.loads((reports / "summary.json").read_text())
    assert set(saved["bars"]) == {
        "no_divergence", "variants_per_plant", "median_ISE_ratio", "worst_ISE_ratio",
        "beats_nominal",
    }  # fmt: skip
    checked = saved["disjoint"]["checked_against"]
    assert (
        checked.startswith("manifest") and "DAgger's fresh variants (seeds 3001..3001)" in checked
    )
    assert summary["pass"] == saved["pass"]
    table = pd.read_csv(reports / "variants.csv")
    assert set(table.columns) == {"system", "variant", "parameter", "value", "factor"}
    assert {p.name for p in (reports / "plots").glob("*.png")} == {
        "ise_ratio_per_plant.png", "gc_vs_nominal.png"
    }  # fmt: skip
    assert summary["bars"]["variants_per_plant"]["min"] == 5
    # the held-out check: the same bar on 5 other variants per plant (seed 4001), step only
    val, held = pd.read_csv(reports / "validation.csv"), saved["validation"]
    assert (held["seed"], held["count"]) == (4001, 5) and set(held["bars"]) == set(saved["bars"])
    assert set(val.scenario) == {"step"} and sorted(val.variant.unique()) == [1, 2, 3, 4, 5]
    assert "DAgger's fresh variants (seeds 3001..3001)" in held["disjoint"]["checked_against"]
    assert len(val[(val.metric == "ISE") & (val.controller == "GC")]) == 2 * 5
    assert held["bars"]["variants_per_plant"]["min"] == 5
    # the set-point check on the nominal plants, in the variants report as well
    setpoint = pd.read_csv(reports / "setpoint.csv")
    assert sorted(setpoint.system) == sorted(set(val.system))
    assert saved["setpoint"]["n_systems"] == len(setpoint)


def test_dagger_rolls_out_on_the_training_variants_the_data_stage_drew():
    from generalist_control.data.generation import training_variants, variants_config
    from generalist_control.training.callbacks import dagger_plants

    nominal = [_fast_plant(), load_plant("two_tank")]
    assert dagger_plants(nominal, {}) == nominal  # without variants: the plants as they are
    on = {
        **TINY,
        "variants": {"enabled": True, "count": 3, "seed": 7, "range": 0.25, "max_tries": 10},
    }
    demos = generate_demos(nominal, on, progress=False)
    manifest = build_manifest(nominal, demos, on, _config(on))
    plants = dagger_plants(nominal, manifest)
    assert [p.name for p in plants] == ["fast"] * 4 + ["two_tank"] * 4
    # the very plants the data stage drew and simulated, rebuilt from the manifest
    steps = demos.r.shape[1]
    grid = np.unique(np.abs(demos.amplitude))
    drawn = training_variants(nominal, variants_config(on), np.concatenate([grid, -grid]), steps)
    for i, p in enumerate(nominal):
        rebuilt = plants[4 * i + 1 : 4 * i + 4]
        for q, v in zip(rebuilt, drawn[p.name].kept, strict=True):
            assert q.tag == p.tag
            np.testing.assert_array_equal(q.A, v.plant.A)
            np.testing.assert_array_equal(q.B, v.plant.B)
            assert q.u_op == v.plant.u_op


def _cstr_hand_case():
    """cstr's A, B, C, the variant A[1,0] x0.8, B x1.3, and both LQI gains (python-control)."""
    plant = load_plant("cstr")
    A_nom, B_nom = np.array([[0.0, 1.0], [-5.47, -4.719]]), np.array([[0.0], [1.0]])
    A_var, B_var = np.array([[0.0, 1.0], [-5.47 * 0.8, -4.719]]), np.array([[0.0], [1.3]])
    C = np.array([[3.199, -1.135]])  # conf/plants/cstr.yaml

    def gains(A, B):
        Aa = np.block([[A, np.zeros((2, 1))], [-C, np.zeros((1, 1))]])
        return np.asarray(control.lqr(Aa, np.vstack([B, [[0.0]]]), plant.Q, plant.R)[0])

    return A_var, B_var, C, gains(A_nom, B_nom), gains(A_var, B_var)


def test_closed_loop_score_keys_variants_by_label_against_their_own_lqi():
    from generalist_control.deploy.adapter import RuntimeAdapter
    from generalist_control.simulation.comparison import ClosedLoopScore

    plant = load_plant("cstr")
    variant = make_variant(plant, {"A[1,0]": 0.8, "B[1]": 1.3})
    nominal_law = RuntimeAdapter(LQIRuntime(["cstr"]))  # the nominal LQI on every row
    got = ClosedLoopScore([plant, variant], [1.0], 6.0, labels=["cstr", "cstr/v1"])(nominal_law)
    A, B, C, k_nom, k_var = _cstr_hand_case()
    # 6 s = 120 steps: 121 samples, y(0) to y(6 s)
    _, y_gc = _discrete_lqi_step(A, B, C, k_nom, 0.05, 121)  # the nominal law on the variant
    _, y_lqi = _discrete_lqi_step(A, B, C, k_var, 0.05, 121)  # the variant's own LQI
    want = float(np.mean((y_gc - y_lqi) ** 2) / np.mean(y_lqi**2))
    assert got["cstr"] == pytest.approx(0.0, abs=1e-20)  # its own law: no error
    assert got["cstr/v1"] == pytest.approx(want, rel=1e-6) and 0.0 < want < 1.0
    with pytest.raises(ValueError, match="one distinct label per plant"):
        ClosedLoopScore([plant, variant], [1.0], 1.0)  # both named cstr


def test_a_scenario_runs_on_the_plants_it_lists_and_an_empty_list_on_none():
    """The variants evaluation picks a scenario's plants as the evaluation does (``runs_on``)."""
    plant = load_plant("cstr")
    factors = {"A[1,0]": 0.9}
    draw = VariantDraw(plant, [Variant(1, make_variant(plant, factors), factors)])
    step = {"kind": "step", "amplitude": 1.0, "duration": 1.0}
    scen = {
        "all": {**step, "plants": None},
        "listed": {**step, "plants": ["cstr"]},
        "other": {**step, "plants": ["two_tank"]},
        "none": {**step, "plants": []},
    }
    df = evaluate_variants(LQIRuntime(["cstr"]), {"cstr": draw}, scen)
    assert set(df.scenario) == {"all", "listed"}
