"""The set-point check: the policy's loop linearised at rest, against hand-built loops."""

from __future__ import annotations

import dataclasses

import control as ct
import numpy as np
import pytest

from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.eval_config import SetpointSettings
from generalist_control.evaluation.runner import run_suite
from generalist_control.evaluation.setpoint import (
    closed_loop_matrix,
    equilibrium,
    setpoint_summary,
)
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import design_lqi
from helpers import lqi_law_policy, net_config, policy_meta

PLANTS = ("cstr", "hydraulic_actuator", "two_tank")  # orders 2, 3 and a nonlinear plant


def _setpoint_check(runtime: PolicyRuntime, names, hold: float = 12, tail: float = 4):
    """The evaluation's set-point check alone: its holds of ``reference`` 1 and the radii."""
    check = SetpointSettings(reference=1.0, hold=hold, tail=tail)
    return run_suite(runtime, [load_plant(n) for n in names], {}, setpoint=check).setpoint


def _radius(A: np.ndarray) -> float:
    return float(np.abs(np.linalg.eigvals(A)).max())


def _sampled(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """python-control's zero-order-hold discretisation of the plant's linear model."""
    p = load_plant(name)
    d = ct.c2d(ct.ss(p.A, p.B, p.C, 0), p.dt, "zoh")
    return np.asarray(d.A), np.asarray(d.B), np.asarray(d.C), p.dt


def _lqi_loop(name: str, k: float = 1.0) -> np.ndarray:
    """Hand-built sampled LQI loop on [x; z], gains times k: z+ = z + dt (r - C x)."""
    Ad, Bd, C, dt = _sampled(name)
    g = design_lqi(load_plant(name))
    n = Ad.shape[0]
    A = np.zeros((n + 1, n + 1))
    A[:n, :n] = Ad - k * Bd @ np.asarray(g.Kx).reshape(1, n)
    A[:n, n] = -k * Bd.ravel() * g.Ki
    A[n, :n] = -dt * C.ravel()
    A[n, n] = 1.0
    return A


def _scaled(k: float):
    def gains(plant):
        g = design_lqi(plant)
        return dataclasses.replace(g, Kx=k * np.asarray(g.Kx), Ki=k * g.Ki)

    return gains


@pytest.mark.parametrize("name", ["cstr", "hydraulic_actuator"])
def test_lqi_law_on_the_newest_sample_has_the_hand_built_spectrum(name):
    """A law on the newest sample only: the window's older samples add only zero eigenvalues."""
    Ad, Bd, C, dt = _sampled(name)
    g = design_lqi(load_plant(name))
    n, H = Ad.shape[0], 5
    jx = np.zeros((H, n))
    jx[-1] = -np.asarray(g.Kx)
    jz = np.zeros(H)
    jz[-1] = -g.Ki
    ours = np.sort_complex(np.linalg.eigvals(closed_loop_matrix(Ad, Bd, C, dt, jx, jz, None)))
    ref = np.linalg.eigvals(_lqi_loop(name))
    expected = np.sort_complex(np.r_[ref, np.zeros(H * (n + 1) - (n + 1))])
    np.testing.assert_allclose(ours, expected, atol=1e-7)


def test_a_law_on_the_oldest_sample_is_a_delayed_loop():
    """Window order: oldest first. A law on sample k-(H-1) is LQI behind an (H-1)-step delay."""
    name, H = "cstr", 3
    Ad, Bd, C, dt = _sampled(name)
    g = design_lqi(load_plant(name))
    n = Ad.shape[0]
    jx = np.zeros((H, n))
    jx[0] = -np.asarray(g.Kx)
    jz = np.zeros(H)
    jz[0] = -g.Ki
    ours = _radius(closed_loop_matrix(Ad, Bd, C, dt, jx, jz, None))
    # hand-built: s = [x, z, q1, q2], q the delayed augmented states' control u = -K [x;z](k-2)
    K = np.r_[np.asarray(g.Kx), g.Ki]
    A = np.zeros((n + 1 + 2, n + 1 + 2))
    A[:n, :n] = Ad
    A[:n, -1] = Bd.ravel()  # u_k = q2 = -K s(k-2)
    A[n, :n], A[n, n] = -dt * C.ravel(), 1.0
    A[n + 1, : n + 1] = -K  # q1(k+1) = -K s(k)
    A[n + 2, n + 1] = 1.0  # q2(k+1) = q1(k)
    assert ours == pytest.approx(_radius(A), rel=1e-9)
    assert ours != pytest.approx(_radius(_lqi_loop(name)), rel=1e-3)  # the delay matters


def test_previous_control_channel_closes_through_the_law():
    """u_k = -K [x; z] + a u_(k-1): hand-built on [x; z; u_(k-1)]."""
    name, a = "hydraulic_actuator", 0.6
    Ad, Bd, C, dt = _sampled(name)
    g = design_lqi(load_plant(name))
    n = Ad.shape[0]
    jx, jz, ju = -np.asarray(g.Kx)[None, :], np.array([-g.Ki]), np.array([a])
    ours = np.sort_complex(np.linalg.eigvals(closed_loop_matrix(Ad, Bd, C, dt, jx, jz, ju)))
    law = np.r_[-np.asarray(g.Kx), -g.Ki, a]
    A = np.zeros((n + 2, n + 2))
    A[:n, :n] = Ad
    A[:n, :] += np.outer(Bd.ravel(), law)
    A[n, :n], A[n, n] = -dt * C.ravel(), 1.0
    A[n + 1, :] = law
    np.testing.assert_allclose(ours, np.sort_complex(np.linalg.eigvals(A)), atol=1e-9)


def test_equilibrium_of_a_linear_plant_holds_the_reference():
    p = load_plant("hydraulic_actuator")
    x, u, r = equilibrium(p, 2.0)
    assert r == 2.0
    np.testing.assert_allclose(p.A @ x + p.B.ravel() * u, 0.0, atol=1e-9)  # at rest
    assert float((p.C @ x)[0]) == pytest.approx(2.0)
    x0, u0, r0 = equilibrium(load_plant("two_tank"), 2.0)  # nonlinear: its operating point
    assert r0 == 0.0 and u0 == 0.0 and not x0.any()


def test_a_policy_that_is_the_lqi_law_settles_as_lqi_does():
    pol, meta = lqi_law_policy(PLANTS, design_lqi)
    df = _setpoint_check(PolicyRuntime(pol, meta), PLANTS)
    assert list(df["system"]) == list(PLANTS)
    for name, row in df.set_index("system").iterrows():
        assert row["radius_GC"] == pytest.approx(_radius(_lqi_loop(str(name))), abs=1e-5)
        assert row["radius_GC"] == pytest.approx(row["radius_LQI"], abs=1e-5)
        assert row["z_star"] == pytest.approx(row["z_LQI"], abs=1e-4)
        assert row["settles"]
        assert row["tail_error_GC"] == pytest.approx(row["tail_error_LQI"], abs=1e-4)
        assert row["tail_du_GC"] == pytest.approx(row["tail_du_LQI"], abs=1e-4)
    assert setpoint_summary(df)["unsettled"] == []


def test_an_unstable_law_is_reported_and_its_hold_does_not_rest():
    """Gains times 12: python-control's sampled loop has radius > 1; the check says so."""
    names = ("cstr", "hydraulic_actuator")
    pol, meta = lqi_law_policy(names, _scaled(12.0))
    df = _setpoint_check(PolicyRuntime(pol, meta), names)
    for name, row in df.set_index("system").iterrows():
        expected = _radius(_lqi_loop(str(name), 12.0))
        assert expected > 1.2
        assert row["radius_GC"] == pytest.approx(expected, rel=1e-5)
        assert not row["settles"]
        assert not row["tail_error_GC"] < 1e-2  # grown, or diverged (NaN)
    summary = setpoint_summary(df)
    assert summary["unsettled"] == sorted(names)
    assert summary["worst_radius_GC"] > 1.2


def test_bad_requests_are_refused_with_the_reason():
    pol = Policy(net_config(hidden=16, experts=2)).eval()
    rt = PolicyRuntime(pol, policy_meta(["cstr"]))
    with pytest.raises(ValueError, match="integral channel"):
        _setpoint_check(rt, ["cstr"], hold=60.0, tail=20.0)
    with pytest.raises(ValueError, match=r"tail must lie in \(0, hold = 5.0\)"):
        SetpointSettings(reference=1.0, hold=5.0, tail=5.0)
