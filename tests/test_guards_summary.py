"""The evaluation summary's GC/LQI ratios against a hand computation.

The policy under evaluation is a real integrating :class:`Policy` whose linear head is the
LQI law at *half* its gains (experts silenced), so GC differs from LQI by a known amount:
the expected ratios come from simulating ``LQIController`` with halved and with full gains
and integrating the errors here with the trapezoidal rule, on the samples the evaluator
scores (``t[:-1]``, ``y[:, :-1]``).
"""

from __future__ import annotations

import numpy as np
import pytest

from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.runner import evaluate
from generalist_control.evaluation.summary import summarise
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import (
    LQIController,
    LQIGains,
    design_lqi,
    sampled_closed_loop,
)
from generalist_control.simulation.scenarios import references
from generalist_control.simulation.simulate import simulate
from helpers import lqi_law_policy

#: Half-gain LQI on these two: worst step ISE ratio 1.166 (hydraulic_actuator), above the
#: 1.15 bar; worst ITAE ratio 1.39 (cstr), below the 2.0 bar.
PLANTS = ("cstr", "hydraulic_actuator")
SCENARIOS = {
    "step": {"kind": "step", "amplitude": 1.0, "duration": 10.0},
    "random_steps": {
        "kind": "random_steps",
        "count": 2,
        "limit": 20.0,
        "seed": 0,
        "duration": 10.0,
    },
}
FACTOR = 0.5


def _half_gains(plant) -> LQIGains:
    g = design_lqi(plant)
    return LQIGains(Kx=FACTOR * g.Kx, Ki=FACTOR * g.Ki, P=g.P, poles=g.poles)


def _half_lqi_policy(names) -> tuple[Policy, dict]:
    """An integrating policy (newest-sample head) whose law is ``-(Kx x + Ki z) / 2``."""
    return lqi_law_policy(names, _half_gains)


def _hand_errors(plant, gains, r) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per run: ISE, ITAE and relative steady-state error of LQI with ``gains``."""
    tr = simulate(plant, LQIController(plant, gains), r)
    assert not tr.diverged.any()
    t = np.arange(r.shape[1]) * plant.dt  # the evaluator's tr.t[:-1]
    e = r - tr.y[:, :-1]
    ise = np.trapezoid(e**2, t, axis=1)
    itae = np.trapezoid(t * np.abs(e), t, axis=1)
    return ise, itae, np.abs(e[:, -1]) / np.abs(r[:, -1])


@pytest.fixture(scope="module")
def evaluated():
    plants = [load_plant(n) for n in PLANTS]
    pol, meta = _half_lqi_policy(PLANTS)
    df, _ = evaluate(PolicyRuntime(pol, meta), plants, SCENARIOS)
    return plants, df


def test_half_gain_lqi_is_a_stable_different_controller():
    for name in PLANTS:
        plant = load_plant(name)
        rho = np.abs(np.linalg.eigvals(sampled_closed_loop(plant, _half_gains(plant)))).max()
        assert rho < 1.0


def test_summary_ratios_match_a_hand_computation(evaluated):
    plants, df = evaluated
    summary = summarise(df)
    hand = {}
    for scen, spec in SCENARIOS.items():
        ise_ratio, itae_ratio, ess = {}, {}, {}
        for p in plants:
            r, x0 = references(scen, spec, p)
            assert x0 is None and r.shape == (spec.get("count", 1), 200)
            ise_gc, itae_gc, ess_gc = _hand_errors(p, _half_gains(p), r)
            ise_lqi, itae_lqi, _ = _hand_errors(p, design_lqi(p), r)
            # the evaluator averages each metric over the runs, then divides GC by LQI
            ise_ratio[p.name] = ise_gc.mean() / ise_lqi.mean()
            itae_ratio[p.name] = itae_gc.mean() / itae_lqi.mean()
            ess[p.name] = ess_gc.mean()
        worst = {
            key: max(values, key=values.get)
            for key, values in (("ISE", ise_ratio), ("ITAE", itae_ratio), ("ess", ess))
        }
        hand[scen] = (ise_ratio[worst["ISE"]], itae_ratio[worst["ITAE"]], ess[worst["ess"]])
        got = summary["ratios"][scen]
        # GC runs the float32 network: it matches the float64 hand loop to about 6e-7
        assert got["worst_ISE_ratio"] == pytest.approx(hand[scen][0], rel=2e-6)
        assert got["worst_ITAE_ratio"] == pytest.approx(hand[scen][1], rel=2e-6)
        assert got["worst_relative_ess_GC"] == pytest.approx(hand[scen][2], rel=1e-4)
        assert got["worst_ISE_system"] == worst["ISE"] == "hydraulic_actuator"
        assert got["worst_ITAE_system"] == worst["ITAE"] == "cstr"
        assert got["worst_relative_ess_system"] == worst["ess"]
        assert got["n_systems"] == len(plants)
    # half the gains: GC is measurably worse than LQI; on the step, ISE beyond the bar
    ise, itae, ess = hand["step"]
    assert 1.15 < ise < 1.2 and 1.2 < itae < 2.0 and ess > 0.01
    bar = summary["quality_bar"]
    assert bar["ISE_ratio_le_1.05"] is False  # hand: 1.166 > 1.05
    assert bar["ITAE_ratio_le_1.25"] is False  # hand: 1.39 > 1.25
    assert bar["ess_within_0.5pct"] is False  # hand: 1.3 % left after 10 s (hydraulic actuator)
    assert bar["stable_everywhere"] is True
    assert summary["diverged"]["GC"] == {}


def test_lqi_itself_is_scored_against_its_own_hand_errors(evaluated):
    """The long-form metrics the summary averages: LQI rows equal the hand ISE per run."""
    plants, df = evaluated
    for p in plants:
        r, _ = references("random_steps", SCENARIOS["random_steps"], p)
        ise, itae, _ = _hand_errors(p, design_lqi(p), r)
        rows = df[
            (df.scenario == "random_steps")
            & (df.controller == "LQI")
            & (df.system == p.name)
            & (df.metric.isin(["ISE", "ITAE"]))
        ].pivot(index="run", columns="metric", values="value")
        np.testing.assert_allclose(rows["ISE"].to_numpy(), ise, rtol=1e-12)
        np.testing.assert_allclose(rows["ITAE"].to_numpy(), itae, rtol=1e-12)
