"""The model card route: the frame and descriptor against python-control, the bank's rows."""

from __future__ import annotations

import dataclasses

import control
import numpy as np
import pytest
import torch

from generalist_control.model.bank import add_plant, add_plants, fit_model_rows
from generalist_control.model.card import (
    CARD_FEATURES,
    CardError,
    card_features,
    card_frame,
)
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.config import plant_from_model
from generalist_control.plants.definition import MAX_ORDER

DURATION = 10.0


def card_config(n_tags: int = 30, hidden: int = 16) -> dict:
    """A small card policy (the default network's parts, the card plant)."""
    base = "generalist_control.model."
    return {
        "_target_": base + "network.GeneralistNetwork",
        "hidden": hidden, "heads": 3, "stride": 2, "experts": 2, "history": 8, "horizon": 3,
        "law_history": None, "channels": ["integral"], "window_scale": True,
        "plant": {"_target_": base + "card.CardPlant", "_partial_": True, "n_tags": n_tags,
                  "hidden": 16, "duration": DURATION},
        "skip": {"_target_": base + "linear.LinearSkip", "_partial_": True, "samples": 1},
    }  # fmt: skip


def _reference_frame(p):
    """The frame by python-control: lqr's poles, c2d's loop, forced_response's step, RMS."""
    K, _, _ = control.lqr(control.ss(p.A, p.B, p.C, 0), p.Q, p.R, integral_action=p.C)
    K = np.asarray(K)
    Kx, Ki = K[0, :-1], -K[0, -1]  # python-control integrates +C x: its Ki flips sign
    n = p.order
    Aa = np.block([[p.A, np.zeros((n, 1))], [-p.C, np.zeros((1, 1))]])
    Ba = np.vstack([p.B, [[0.0]]])
    poles = np.linalg.eigvals(Aa - Ba @ np.append(Kx, Ki)[None, :])
    omega = np.exp(np.mean(np.log(np.abs(poles))))
    T = np.array([p.C[0] @ np.linalg.matrix_power(p.A / omega, i) for i in range(n)])
    sysd = control.c2d(control.ss(p.A, p.B, np.eye(n), 0), p.dt, "zoh")
    Ad, Bd = np.asarray(sysd.A), np.asarray(sysd.B)
    Phi = np.block([[Ad - Bd @ Kx[None, :], -Bd * Ki], [-p.dt * p.C, np.ones((1, 1))]])
    Gam = np.vstack([np.zeros((n, 1)), [[p.dt]]])
    steps = int(round(DURATION / p.dt))
    loop = control.ss(Phi, Gam, np.eye(n + 1), 0, p.dt)
    _, s = control.forced_response(loop, T=np.arange(steps) * p.dt, U=np.ones(steps))
    s = np.asarray(s).T  # (steps, n + 1)
    u = -(s[:, :n] @ Kx + Ki * s[:, n])
    rms = lambda v: np.sqrt(np.mean(v**2, axis=0))  # noqa: E731
    sq = rms(s[:, :n] @ T.T)
    return T / sq[:, None], rms(s[:, :n]), float(rms(s[:, n])), float(rms(u)), omega


@pytest.mark.parametrize("name", ["cstr", "magnetic_levitation", "two_mass_spring"])
def test_frame_matches_python_control(name):
    p = load_plant(name)
    frame = card_frame(p, DURATION)
    T, sx, sz, su, omega = _reference_frame(p)
    np.testing.assert_allclose(frame.omega, omega, rtol=1e-9)
    np.testing.assert_allclose(frame.map, T, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(frame.state, sx, rtol=1e-7)
    np.testing.assert_allclose([frame.integral, frame.control], [sz, su], rtol=1e-7)


@pytest.mark.parametrize("name", ["cstr", "hydraulic_actuator", "flexible_joint"])
def test_descriptor_is_the_experts_gain_in_the_frame(name):
    """The order mask, then asinh of python-control's LQI gain carried into the frame; that
    gain on the frame's [q; z] gives the expert's control over its scale."""
    p = load_plant(name)
    frame = card_frame(p, DURATION)
    f = card_features(p, frame)
    n = p.order
    assert f.shape == (CARD_FEATURES,) == (2 * MAX_ORDER + 1,)
    np.testing.assert_array_equal(f[:MAX_ORDER], (np.arange(MAX_ORDER) < n).astype(float))
    K, _, _ = control.lqr(control.ss(p.A, p.B, p.C, 0), p.Q, p.R, integral_action=p.C)
    Kx, Ki = np.asarray(K)[0, :-1], -K[0, -1]  # python-control's integral flips sign
    M_ref, _, s_z, s_u, _ = _reference_frame(p)
    gain = np.zeros(MAX_ORDER + 1)
    gain[[*range(n), MAX_ORDER]] = np.append(Kx @ np.linalg.inv(M_ref), Ki * s_z) / s_u
    np.testing.assert_allclose(f[MAX_ORDER:], np.arcsinh(gain), rtol=1e-6, atol=1e-8)
    x, z = np.random.default_rng(0).normal(size=(5, n)), np.linspace(-1.0, 1.0, 5)
    w = np.hstack([x @ frame.map.T, z[:, None] / frame.integral])
    np.testing.assert_allclose(-w @ frame.gain, -(x @ Kx + Ki * z) / frame.control, rtol=1e-6)


def _transformed(p, S):
    """The same plant in the coordinates ``x' = S x`` (weights carried along)."""
    Si = np.linalg.inv(S)
    Sa = np.eye(p.order + 1)
    Sa[: p.order, : p.order] = Si
    return dataclasses.replace(
        p, name=p.name + "_b", A=S @ p.A @ Si, B=S @ p.B, C=p.C @ Si, Q=Sa.T @ p.Q @ Sa
    )


def test_every_realisation_gives_the_same_card_and_network_inputs():
    p = load_plant("hydraulic_actuator")
    S = np.array([[2.0, 0.5, 0.0], [0.0, -30.0, 1.0], [0.3, 0.0, 0.01]])
    q = _transformed(p, S)
    fp, fq = card_frame(p, DURATION), card_frame(q, DURATION)
    np.testing.assert_allclose(card_features(q, fq), card_features(p, fp), atol=1e-6)
    np.testing.assert_allclose(fq.map @ S, fp.map, rtol=1e-8, atol=1e-10)  # q = map x


def test_frame_refuses_an_unobservable_model():
    A = np.diag([-1.0, -2.0])
    model = {"A": A, "B": [[1.0], [1.0]], "C": [[1.0, 0.0]], "dt": 0.05, "Q": [1, 1, 1], "R": 1}
    with pytest.raises(CardError, match="not observable from its output"):
        card_frame(plant_from_model(model, "hidden_mode"), DURATION)


def test_bank_rows_and_a_plant_added_leave_every_trained_value_alone():
    torch.manual_seed(0)
    policy = Policy(card_config())
    trained = [load_plant(n) for n in ("cstr", "dc_servo", "unstable")]
    fit_model_rows(policy, trained)
    frame = card_frame(trained[0], DURATION)
    norm = policy.normaliser
    np.testing.assert_allclose(norm.state_map[trained[0].tag, :2, :2].numpy(), frame.map)
    assert float(norm.control_scale[trained[0].tag]) == pytest.approx(frame.control)
    assert float(norm.state_scale[trained[0].tag, MAX_ORDER]) == pytest.approx(frame.integral)
    grown = add_plant(policy, load_plant("magnetic_levitation"))
    assert grown.net.n_tags == policy.net.n_tags + 1
    old = policy.state_dict()
    for key, value in grown.state_dict().items():
        same = value[: old[key].shape[0]] if value.shape != old[key].shape else value
        assert torch.equal(same, old[key]), key
    x, m = torch.randn(4, 8, 5), torch.ones(4, 8, 5)
    r, tag = torch.randn(4, 8), torch.tensor([10, 14, 23, 10])
    torch.testing.assert_close(grown(x, m, r, tag)[0], policy(x, m, r, tag)[0], rtol=0, atol=0)


def test_plants_added_at_once_are_those_added_one_at_a_time():
    torch.manual_seed(0)
    policy = Policy(card_config())
    fit_model_rows(policy, [load_plant(n) for n in ("cstr", "dc_servo")])
    new = [load_plant("magnetic_levitation"), load_plant("flexible_joint")]
    together, apart = add_plants(policy, new), add_plant(add_plant(policy, new[0]), new[1])
    assert together.net.n_tags == policy.net.n_tags + 2
    for key, value in apart.state_dict().items():
        assert torch.equal(together.state_dict()[key], value), key
    for tag, p in zip((30, 31), new, strict=True):
        card = card_features(p, card_frame(p, DURATION))
        np.testing.assert_allclose(together.net.plant.cards[tag].numpy(), card, rtol=1e-6)


def test_padded_state_entries_reach_the_network_as_zeros():
    policy = Policy(card_config())
    p = load_plant("cstr")
    fit_model_rows(policy, [p])
    x = torch.randn(2, 8, 5)
    mask = torch.ones(2, 8, 5)
    mask[..., p.order : MAX_ORDER] = 0
    tag = torch.full((2,), p.tag)
    state, *_ = policy.normaliser.normalise_inputs(x * mask, mask, torch.randn(2, 8), tag)
    assert torch.all(state[..., p.order : MAX_ORDER] == 0)
    frame = card_frame(p, DURATION)
    expect = torch.einsum("ij,btj->bti", torch.as_tensor(frame.map).float(), x[..., :2])
    torch.testing.assert_close(state[..., :2], expect, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(state[..., MAX_ORDER], x[..., MAX_ORDER] / frame.integral)
