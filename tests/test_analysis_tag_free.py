"""The tag-free stage's analyses (analysis/, research): the bar and its diagnostics."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch

from generalist_control.model.policy import Policy, load_policy
from helpers import compose_cfg, net_config, tiny_train_overrides


def _inferred():
    return net_config(channels=["integral", "previous_control"], skip="context",
                      plant="inferred", models=None)  # fmt: skip


def _long(rows):
    return pd.DataFrame(
        rows, columns=["system", "scenario", "controller", "run", "metric", "value"]
    )


def test_tag_free_bar_counts_ratios_and_divergence_by_hand():
    from analysis.tag_free import tag_free_bar

    rows = []
    for system, gc, lqi in (("a", 1.0, 1.0), ("b", 2.6, 2.0), ("c", 1.2, 1.0)):
        rows += [(system, "step", "GC", 0, "ISE", gc), (system, "step", "LQI", 0, "ISE", lqi)]
        rows += [(system, "step", "GC", 0, "diverged", 0.0)]
    rows += [("c", "sine", "GC", 0, "diverged", 1.0), ("a", "sine", "LQI", 0, "diverged", 1.0)]
    bar = tag_free_bar(_long(rows), ise_ratio=1.25, min_plants=2)
    assert bar["step_ise_ratio"] == pytest.approx({"a": 1.0, "b": 1.3, "c": 1.2})
    assert bar["missing"] == ["b"] and bar["passed"] == 2 and bar["step_ise_ratio_met"]
    assert bar["diverged"] == ["c/sine"]  # LQI's divergence is not GC's
    assert not bar["no_divergence"] and not bar["met"]
    assert not tag_free_bar(_long(rows), min_plants=3)["step_ise_ratio_met"]


def test_separation_finds_a_twin_and_parts_plants_of_another_order_at_once():
    import dataclasses

    from analysis.separation import separation_table

    from generalist_control.plants.catalog import load_plant

    cstr, hyd = load_plant("cstr"), load_plant("hydraulic_actuator")
    twin = dataclasses.replace(cstr, name="cstr_twin")
    policy = Policy(net_config(channels=["integral"], window_scale=True))
    table = separation_table(policy, [cstr, twin, hyd], duration=1.0).set_index("system")
    assert table.loc["cstr", "nearest"] == "cstr_twin"
    assert table.loc["cstr", "input_gap"] == 0 and table.loc["cstr", "control_gap"] == 0
    assert table.loc["cstr", "separation_time"] == float("inf")
    assert table.loc["hydraulic_actuator", "separation_time"] == pytest.approx(cstr.dt)


def _traj(y, r, diverged):
    from generalist_control.simulation.simulate import Trajectory

    y, r = np.atleast_2d(y), np.atleast_2d(r)
    t = np.arange(r.shape[1] + 1) * 0.05
    x = y[..., None]
    return Trajectory(t=t, x=x, u=np.zeros_like(r), r=r, y=y, diverged=np.asarray(diverged))


def test_departures_place_each_diverged_run_on_its_reference_level_by_hand():
    """Level changes at samples 20 and 40; GC leaves at 46 (level 2) or at 6 (level 0)."""
    from analysis.departures import COLUMNS, departure_summary
    from analysis.departures import departure_table as table

    r = np.repeat([1.0, 3.0, 5.0], 20)
    lqi_y = np.append(r - 1.0, r[-1] - 1.0)  # the expert's tracking error: 1 throughout
    late, early, fine = lqi_y.copy(), lqi_y.copy(), lqi_y.copy()
    late[47:] = 1e7
    late[46] = 5.0 + 3.5  # error 3.5 > 3 x 1 first at sample 46 (level 2, 6 samples in)
    early[6:] = np.nan  # a non-finite output counts
    sine = np.sin(np.arange(60) * 0.3)
    sine_lqi = np.append(sine - 0.1, 0.0)
    sine_gc = sine_lqi.copy()
    sine_gc[30:] = 50.0
    trajs = {
        "staircase": {
            "GC": {"p": _traj(np.stack([late, early, fine]), np.stack([r] * 3), [1, 1, 0])},
            "LQI": {"p": _traj(np.stack([lqi_y] * 3), np.stack([r] * 3), [0, 0, 0])},
        },
        "sine": {
            "GC": {"q": _traj(sine_gc, sine, [1])},
            "LQI": {"q": _traj(sine_lqi, sine, [0])},
        },
        "step": {"GC": {"p": _traj(lqi_y, r, [1])}},  # no LQI runs: left out
    }
    got = table(trajs)
    assert list(got.columns) == COLUMNS
    rows = {(s, run): row for _, s, run, *row in got.itertuples(index=False, name=None)}
    assert set(rows) == {("staircase", 0), ("staircase", 1), ("sine", 0)}
    np.testing.assert_allclose(rows["staircase", 0][:3], [46 * 0.05, 2, 6 * 0.05])
    np.testing.assert_allclose(rows["staircase", 1][:3], [6 * 0.05, 0, 6 * 0.05])
    assert rows["sine", 0][0] == pytest.approx(30 * 0.05)
    assert np.isnan(rows["sine", 0][1]) and np.isnan(rows["sine", 0][2])
    assert departure_summary(got) == {
        "runs": 3,
        "on_first_level": 1,
        "after_a_later_change": 1,
        "continuous_reference": 1,
        "median_t_leave_s": pytest.approx(30 * 0.05),
    }
    # a run lost through another state: its output stays within 3x, its state freezes at 30
    stuck = lqi_y + 0.001 * np.arange(61)
    stuck[30:] = stuck[30]
    other = {"staircase": {"GC": {"p": _traj(stuck, r, [1])}, "LQI": {"p": _traj(lqi_y, r, [0])}}}
    np.testing.assert_allclose(table(other).iloc[0, 3:], [30 * 0.05, 1, 10 * 0.05])
    # a looser factor lets the error of 3.5 pass: the late run leaves one sample later
    assert table(trajs, factor=4.0).set_index(["scenario", "run"]).loc[
        ("staircase", 0), "t_leave"
    ] == pytest.approx(47 * 0.05)


def test_identity_table_reads_the_head_on_each_plant_s_expert_step():
    """A head whose output is its bias alone: p_true is the softmax of the bias over the
    plants, at each of the times asked; a policy without the head is refused."""
    from analysis.identity import identity_table

    from generalist_control.plants.catalog import load_plant

    plants = [load_plant(n) for n in ("cstr", "two_tank", "hydraulic_actuator")]
    policy = Policy(_inferred()).eval()
    head = policy.net.plant.head
    with torch.no_grad():
        head.weight.zero_()
        head.bias.zero_()
        head.bias[plants[1].tag] = 2.0
    table = identity_table(policy, plants, times=(0.1, 0.5))
    assert list(table.time.unique()) == pytest.approx([0.1, 0.5])
    p_two_tank = math.exp(2.0) / (math.exp(2.0) + 2.0)
    for name, group in table.groupby("system"):
        expected = p_two_tank if name == "two_tank" else 1.0 / (math.exp(2.0) + 2.0)
        assert group.p_true.to_numpy() == pytest.approx([expected] * 2)
        assert (group.guess == "two_tank").all()
    with pytest.raises(ValueError, match="has no identity head"):
        identity_table(Policy(net_config(skip="linear", channels=["integral"])), plants)


def test_identity_trace_reads_the_head_on_the_runtime_s_own_windows():
    """Before the hand-over the runtime's windows are the expert's closed loop: the traced
    probabilities there equal the head's on the windows the window builder cuts from the
    expert's own step (identity_table), sample by sample."""
    from analysis.identity import (
        identity_summary,
        identity_table,
        identity_trace,
    )

    from generalist_control.deploy.runtime import PolicyRuntime
    from generalist_control.plants.catalog import load_plant
    from helpers import policy_meta

    names = ["cstr", "two_tank"]
    plants = [load_plant(n) for n in names]
    torch.manual_seed(0)
    policy = Policy(_inferred()).eval()
    with torch.no_grad():
        torch.nn.init.normal_(policy.net.plant.head.weight)  # a head that tells windows apart
    spec = {"kind": "step", "amplitude": 1.0, "duration": 1.0}
    trace = identity_trace(PolicyRuntime(policy, policy_meta(names)), plants, spec, [0, 5])
    assert set(trace.handover_samples) == {0, 5}
    part = trace[trace.handover_samples == 5]
    assert len(part) == 2 * 20 and set(part.system) == set(names)
    table = identity_table(policy, plants, times=(0.05, 0.1, 0.2))
    expert = part.assign(time=part.time.round(6)).set_index(["system", "time"]).p_true
    reference = table.assign(time=table.time.round(6)).set_index(["system", "time"]).p_true
    assert len(set(reference.round(6))) > 2  # the head's answers differ by plant and time
    for key, value in reference.items():
        assert expert[key] == pytest.approx(value, rel=1e-4)
    summary = identity_summary(table, trace)
    assert set(summary) == {"0.05", "0.1", "0.2", "own_from_0", "own_from_5"}
    assert set(summary["own_from_5"]) == set(names)


@pytest.mark.slow
def test_the_tag_free_stage_trains_evaluates_and_writes_its_analyses(
    tiny_data_dir, tmp_path, mlflow_uri
):
    """experiment=tag_free end to end on tiny data: train, evaluate, then the analyses."""
    from analysis.run_tag_free import run as analyse

    from generalist_control.evaluate import run as evaluate_run
    from helpers import train

    switch = (
        "experiment=tag_free",
        "dagger.start_epoch=1",
        "dagger.rounds=1",
        "logger.log_model=false",
    )
    overrides = tiny_train_overrides(tiny_data_dir, tmp_path / "tf", mlflow_uri, *switch)
    _, objects = train(compose_cfg(*overrides))
    policy, _ = load_policy(objects["policy_path"])
    models = policy.net.plant.identifier.models
    assert models.params.weight.abs().max() > 0  # the one-step models were trained
    assert models.lags == (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6) and models.offset
    trained = objects["trainer"].lightning_module.policy.net.plant
    assert trained.noise == 0.02 and (policy.history, policy.net.law_history) == (24, 8)
    (cb,) = [c for c in objects["trainer"].callbacks if type(c).__name__ == "DAggerCallback"]
    assert cb.done == 1 and cb.history[0]["windows"] > 0
    actuator = cb.sampler.settings.actuator
    assert (actuator.lag, actuator.offset) == (1.0, 0.3)
    reports, bar_dir = tmp_path / "reports", tmp_path / "bar"
    base = [*overrides, f"policy={objects['policy_path']}", f"paths.reports_dir={reports}"]
    ecfg = compose_cfg(*base, "evaluation.plots=false", "evaluation.setpoint=null")
    from omegaconf import OmegaConf, open_dict

    with open_dict(ecfg):
        ecfg.evaluation.scenarios = OmegaConf.create(
            {"step": {"kind": "step", "amplitude": 1.0, "duration": 5.0}}
        )
        ecfg.evaluation.crazyflie = None
    evaluate_run(ecfg)
    with open_dict(ecfg):
        ecfg.analysis = {"out": str(bar_dir), "handover": [0, 1, 5], "gain_samples": 5}
    bar = analyse(ecfg)
    assert json.loads((bar_dir / "bar.json").read_text())["met"] == bar["met"]
    f = pd.read_csv(reports / "metrics.csv")
    ise = f[(f.scenario == "step") & (f.metric == "ISE")].set_index(["controller", "system"]).value
    assert bar["step_ise_ratio"] == pytest.approx((ise["GC"] / ise["LQI"]).to_dict())
    handover = pd.read_csv(bar_dir / "handover.csv")
    assert sorted(set(handover.handover_samples)) == [0, 1, 5]
    start = handover[handover.handover_samples == 0].set_index("system")
    for system, ratio in bar["step_ise_ratio"].items():  # N = 0: the evaluation's own GC run
        if start.diverged[system] == 0:
            assert start.ise_ratio[system] == pytest.approx(ratio, rel=1e-9)
    named = pd.read_csv(bar_dir / "identity.csv")
    assert set(named.system) == {"cstr", "hydraulic_actuator"}
    assert named.p_true.between(0, 1).all() and (named.p_guess >= named.p_true - 1e-12).all()
    departures = pd.read_csv(bar_dir / "departures.csv")  # a DVC output even when empty
    assert len(departures) == bar["departures"]["runs"]
    separation = pd.read_csv(bar_dir / "separation.csv")
    assert set(separation.system) == {"cstr", "hydraulic_actuator"}
