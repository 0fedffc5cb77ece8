"""The hand-over diagnostic (analysis/) and the runtime's record of the control applied."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch
from analysis.handover import Handover, handover_summary, handover_table

from generalist_control.data.windows import build_windows, integral_of_error
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.definition import pad_states
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.simulate import Run, simulate, simulate_many
from helpers import lqi_law_policy, net_config, policy_meta

PLANTS = ("cstr", "hydraulic_actuator")  # orders 2 and 3
STEPS = 60


def _controls_policy() -> Policy:
    """A random tag-free policy that reads its previous control (the skip gains given weight)."""
    torch.manual_seed(0)
    config = net_config(hidden=16, experts=2, channels=["integral", "previous_control"],
                        skip="context", plant="inferred", models=None)  # fmt: skip
    pol = Policy(config).eval()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        pol.net.skip.gains.weight.normal_(0.0, 0.02, generator=g)
        pol.normaliser.state_scale[:, -1] = 10.0  # its feedback on its own control: bounded
    return pol


def _runs(amplitudes=(1.0, -2.0)) -> list[Run]:
    refs = np.repeat(np.array(amplitudes)[:, None], STEPS, axis=1)
    return [Run(load_plant(n), refs) for n in PLANTS]


def test_recorded_control_is_the_previous_control_the_policy_reads():
    """Stepped along an LQI run and told LQI's controls, the runtime's plans are the network
    on the windows the window builder makes of that run (LQI's controls in the channel)."""
    pol = _controls_policy()
    runtime = PolicyRuntime(pol, policy_meta(PLANTS))
    plant = load_plant("hydraulic_actuator")
    tr = simulate(plant, LQIController(plant), np.full((1, STEPS), 1.5))
    runtime.reset(plant.name)
    plans = []
    for k in range(STEPS):
        runtime.step(tr.x[0, k], tr.r[0, k])
        runtime.record_applied(tr.u[0, k])
        plans.append(runtime.plan[0])
    z = integral_of_error(tr.r, tr.y[:, :-1], plant.dt)
    w = build_windows(
        pad_states(tr.x[:, :-1]), tr.r, tr.u, np.array([plant.tag]), np.array([plant.order]),
        8, 1, z, True,
    )  # fmt: skip
    expected, _ = pol.predict_windows(w)
    np.testing.assert_allclose(np.array(plans), expected, rtol=1e-5, atol=1e-6)
    assert np.abs(np.array(plans)[:, 0] - tr.u[0]).max() > 0.1  # LQI's controls, not its own


def test_recording_a_control_refuses_a_wrong_length_and_nan():
    runtime = PolicyRuntime(_controls_policy(), policy_meta(PLANTS))
    runtime.reset(list(PLANTS))
    runtime.step(np.zeros((2, 4)), np.ones(2))
    with pytest.raises(ValueError, match=r"shape \(3,\); expected \(2,\)"):
        runtime.record_applied([0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match=r"not finite in rows \[1\]"):
        runtime.record_applied([0.0, np.nan])


def test_handover_at_zero_is_the_policy_and_past_the_end_is_lqi():
    pol = _controls_policy()
    runtime = PolicyRuntime(pol, policy_meta(PLANTS))
    runs = _runs()
    own = simulate_many(runs, RuntimeAdapter(runtime))
    lqi = [simulate(r.plant, LQIController(r.plant), r.r) for r in runs]
    for got, ref in zip(simulate_many(runs, Handover(runtime, 0)), own, strict=True):
        np.testing.assert_array_equal(got.u, ref.u)
    for got, ref in zip(simulate_many(runs, Handover(runtime, STEPS)), lqi, strict=True):
        np.testing.assert_allclose(got.u, ref.u, rtol=1e-12, atol=1e-12)
    assert max(np.abs(o.u - q.u).max() for o, q in zip(own, lqi, strict=True)) > 0.1


def test_the_policy_takes_over_from_the_experts_closed_loop():
    """Before sample N the controls are LQI's; at N the policy's answer to the window of
    LQI's own run (states, integral and LQI's controls), as built by the window builder."""
    pol, n = _controls_policy(), 7
    runtime = PolicyRuntime(pol, policy_meta(PLANTS))
    runs = _runs()
    got = simulate_many(runs, Handover(runtime, n))
    for run, tr in zip(runs, got, strict=True):
        p = run.plant
        lqi = simulate(p, LQIController(p), run.r)
        np.testing.assert_allclose(tr.u[:, :n], lqi.u[:, :n], rtol=1e-12, atol=1e-12)
        z = integral_of_error(lqi.r, lqi.y[:, :-1], p.dt)
        w = build_windows(
            pad_states(lqi.x[:, : n + 1]), lqi.r[:, : n + 1], lqi.u[:, : n + 1],
            np.full(2, p.tag), np.full(2, p.order), 8, 1, z[:, : n + 1], True,
        )  # fmt: skip
        expected, _ = pol.predict_windows(w)
        # float32: the runtime's one window and the batch sum in other orders on some CPUs
        # (1e-7 apart on an AVX-512 Xeon); the controls are O(1)
        expect = expected[:, 0].reshape(2, n + 1)[:, n]
        np.testing.assert_allclose(tr.u[:, n], expect, rtol=1e-5, atol=1e-6)
        assert np.abs(tr.u[:, n] - lqi.u[:, n]).max() > 1e-3  # the policy, not the expert


def test_handover_table_of_the_lqi_law_is_lqi_at_every_handover():
    """A policy that is the LQI law gives LQI's ISE whoever starts; nothing diverges."""
    pol, meta = lqi_law_policy(PLANTS, design_lqi)
    spec = {"kind": "step", "amplitude": 1.0, "duration": 5.0}
    table = handover_table(PolicyRuntime(pol, meta), [load_plant(n) for n in PLANTS], spec, (0, 3))
    assert list(table.columns) == [
        "system", "handover_samples", "handover_s", "diverged", "runs", "ise_ratio"
    ]  # fmt: skip
    assert len(table) == 4 and (table.diverged == 0).all() and (table.runs == 1).all()
    np.testing.assert_allclose(table.ise_ratio, 1.0, rtol=1e-4)
    assert table.handover_s.tolist() == pytest.approx([0.0, 0.0, 0.15, 0.15])


def test_handover_summary_names_the_diverged_and_counts_the_ratios_by_hand():
    table = pd.DataFrame(
        {
            "system": ["a", "b", "c", "a", "b", "c"],
            "handover_samples": [0, 0, 0, 10, 10, 10],
            "handover_s": [0.0, 0.0, 0.0, 0.5, 0.5, 0.5],
            "diverged": [1, 0, 0, 0, 0, 0],
            "runs": [1] * 6,
            "ise_ratio": [np.nan, 2.0, 1.1, 1.3, 1.2, 1.0],
        }
    )
    out = handover_summary(table, 1.25)
    assert out["0"] == {
        "handover_s": 0.0, "plants_diverged": ["a"], "plants_within_ise_ratio": 1, "plants": 3
    }  # fmt: skip
    assert out["10"]["plants_diverged"] == [] and out["10"]["plants_within_ise_ratio"] == 2


def test_local_gains_of_the_lqi_law_are_lqis_gains():
    """For a policy that is the LQI law the derivative at the newest sample is -Kx, -Ki."""
    from analysis.local_gains import local_gains

    pol, meta = lqi_law_policy(PLANTS, design_lqi)
    plants = [load_plant(n) for n in PLANTS]
    spec = {"kind": "step", "amplitude": 1.0, "duration": 5.0}
    gains = local_gains(PolicyRuntime(pol, meta), plants, spec, samples=12)
    assert gains.input.tolist() == ["x1", "x2", "z", "x1", "x2", "x3", "z"]
    for p in plants:
        part = gains[gains.system == p.name]
        g = design_lqi(p)
        np.testing.assert_allclose(part.lqi, [*-g.Kx, -g.Ki], rtol=1e-12)
        np.testing.assert_allclose(part.policy, part.lqi, rtol=1e-4)
        scale = pol.normaliser.state_scale[p.tag].double().numpy()[[*range(p.order), 4]]
        su = float(pol.normaliser.control_scale[p.tag])
        np.testing.assert_allclose(part.lqi_norm, part.lqi * scale / su, rtol=1e-12)
    with pytest.raises(ValueError, match="lasts 100 samples; local gains after 100 need"):
        local_gains(PolicyRuntime(pol, meta), plants, spec, samples=100)


def test_local_gains_list_the_previous_control_and_the_summary_flags_a_wrong_sign():
    from analysis.local_gains import gain_summary, local_gains

    spec = {"kind": "step", "amplitude": 1.0, "duration": 5.0}
    gains = local_gains(
        PolicyRuntime(_controls_policy(), policy_meta(PLANTS)), [load_plant("cstr")], spec, 5
    )
    assert gains.input.tolist() == ["x1", "x2", "z", "u_prev"]
    assert np.isnan(gains.ratio.iloc[-1]) and gains.lqi.iloc[-1] == 0.0
    table = pd.DataFrame(
        {
            "system": ["a", "a", "a", "a"],
            "input": ["x1", "x2", "z", "u_prev"],
            "lqi_norm": [-4.0, 3.0, 9.0, 0.0],
            "policy_norm": [8.0, 0.0, 0.0, 1.0],
        }
    )
    summary = gain_summary(table)  # over x only: |(8, 0)| / |(-4, 3)| = 1.6
    expected = {"norm_ratio": pytest.approx(1.6), "largest": "x1", "same_sign": False}
    assert summary == {"a": expected}
