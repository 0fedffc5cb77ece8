"""The window builder: counts, shapes, padding, masks and alignment with the raw signals."""

import numpy as np
import pytest

from generalist_control.data.windows import (
    HistoryBuffer,
    build_windows,
    history_windows,
    previous_controls,
)
from generalist_control.plants.definition import pad_states

H, K = 8, 3


def toy(B=3, N=20, orders=(2, 3, 4)):
    rng = np.random.default_rng(1)
    x = np.zeros((B, N, 4))
    for b, n in enumerate(orders):
        x[b, :, :n] = rng.normal(size=(N, n))
    return x, rng.normal(size=(B, N)), rng.normal(size=(B, N)), np.array(orders)


def test_counts_and_shapes():
    x, r, u, order = toy()
    w = build_windows(x, r, u, np.array([5, 6, 7]), order, H, K)
    assert len(w) == 3 * (20 - K + 1)
    assert w.state.shape == (54, H, 4) and w.mask.shape == (54, H, 4)
    assert w.ref.shape == (54, H) and w.target.shape == (54, K)
    assert w.state.dtype == np.float32 and w.tag.dtype == np.int64
    assert w.tag.tolist() == [5] * 18 + [6] * 18 + [7] * 18
    assert w.traj.tolist() == [0] * 18 + [1] * 18 + [2] * 18


def test_alignment_with_raw_signals():
    x, r, u, order = toy()
    w = build_windows(x, r, u, np.zeros(3, int), order, H, K)
    per = 20 - K + 1
    for b in range(3):
        for k in (0, 3, 7, 10, per - 1):
            i = b * per + k
            idx = np.clip(np.arange(k - H + 1, k + 1), 0, None)  # edge-padded history
            np.testing.assert_allclose(w.state[i], x[b, idx].astype(np.float32))
            np.testing.assert_allclose(w.ref[i], r[b, idx].astype(np.float32))
            np.testing.assert_allclose(w.target[i], u[b, k : k + K].astype(np.float32))


def test_mask_and_zero_padding():
    x, r, u, order = toy()
    for b, n in enumerate(order):
        x[b, :, n:] = 99.0  # junk in the padded entries must not leak through
    w = build_windows(x, r, u, np.zeros(3, int), order, H, K)
    per = 20 - K + 1
    for b, n in enumerate(order):
        sl = slice(b * per, (b + 1) * per)
        assert np.all(w.mask[sl, :, :n] == 1) and np.all(w.mask[sl, :, n:] == 0)
        assert np.all(w.state[sl, :, n:] == 0)


def test_history_windows_last_equals_build_windows():
    x, r, u, order = toy()
    s, m, rr = history_windows(x, r, order, H)
    w = build_windows(x, r, u, np.zeros(3, int), order, H, K)
    np.testing.assert_array_equal(s[0, 5], w.state[5])
    np.testing.assert_array_equal(rr[2, 17], w.ref[2 * 18 + 17])


def test_pad_states_rejects_too_many_states():
    assert pad_states(np.ones((2, 3))).shape == (2, 4)
    with pytest.raises(ValueError, match="at most 4"):
        pad_states(np.ones((2, 5)))


def test_integral_channel_is_the_lqi_experts_own_integrator():
    """The error integral equals LQIController's z before each control, on a nonlinear plant."""
    from generalist_control.data.windows import HistoryBuffer, integral_of_error
    from generalist_control.plants.catalog import load_plant
    from generalist_control.simulation.lqi import LQIController
    from generalist_control.simulation.simulate import simulate

    plant = load_plant("two_tank")
    ctrl = LQIController(plant)
    seen = []

    class Recording:
        def reset(self, batch_size):
            ctrl.reset(batch_size)

        def step(self, x, r):
            seen.append(ctrl.z.copy())
            return ctrl.step(x, r)

    r = np.array([[1.0] * 30 + [-2.0] * 30, [3.0] * 60]) * plant.amplitude_scale
    tr = simulate(plant, Recording(), r)
    z = integral_of_error(tr.r, tr.y[:, :-1], plant.dt)
    np.testing.assert_allclose(z, np.stack(seen, axis=1), rtol=0, atol=1e-13)
    # as the last state channel: always valid, after the (masked) padding
    x = pad_states(tr.x[:, :-1])
    order = np.full(2, plant.order)
    w = build_windows(x, tr.r, tr.u, np.full(2, plant.tag), order, H, K, z)
    assert w.state.shape[1:] == (H, 5) and w.mask[:, :, 4].min() == 1.0
    assert np.all(w.mask[:, :, plant.order : 4] == 0) and np.all(w.state[:, :, 2:4] == 0)
    keep = 60 - K + 1
    np.testing.assert_allclose(w.state[:keep, -1, 4], z[0, :keep].astype(np.float32))
    # the online buffer builds the same windows
    buf = HistoryBuffer(order, H, integral=True)
    for k in range(keep):
        state, mask, ref = buf.push(x[:, k].astype(np.float32), tr.r[:, k], z[:, k])
        np.testing.assert_array_equal(state[0], w.state[k])
        np.testing.assert_array_equal(mask[1], w.mask[keep + k])
    with pytest.raises(ValueError, match="keeps the error integral"):
        buf.push(x[:, 0].astype(np.float32), tr.r[:, 0])


def test_previous_control_channel_is_u_one_sample_earlier_online_and_offline():
    """model.control_history: the last channel is u[k-1] (0 at k = 0), after the integral."""
    x, r, u, order = toy()
    z = np.cumsum(r, axis=1)  # any signal will do for the integral channel here
    prev = previous_controls(u)
    np.testing.assert_array_equal(prev[:, 0], 0.0)
    np.testing.assert_array_equal(prev[:, 1:], u[:, :-1])
    w = build_windows(x, r, u, np.zeros(3, int), order, H, K, z, controls=True)
    assert w.state.shape[1:] == (H, 6) and np.all(w.mask[:, :, 4:] == 1.0)
    per = 20 - K + 1
    for b in range(3):
        for k in (0, 1, 5, per - 1):
            idx = np.clip(np.arange(k - H + 1, k + 1), 0, None)
            expected = np.where(np.arange(k - H + 1, k + 1) >= 1, u[b, idx - 1], 0.0)
            expected[np.arange(k - H + 1, k + 1) < 0] = 0.0  # front padding repeats u[-1] = 0
            np.testing.assert_allclose(w.state[b * per + k, :, 5], expected.astype(np.float32))
            np.testing.assert_allclose(w.state[b * per + k, :, 4], z[b, idx].astype(np.float32))
    buf = HistoryBuffer(order, H, integral=True, controls=True)
    for k in range(per):
        state, mask, _ = buf.push(x[:, k].astype(np.float32), r[:, k], z[:, k], prev[:, k])
        np.testing.assert_array_equal(state, w.state[k::per])
        np.testing.assert_array_equal(mask, w.mask[k::per])
    with pytest.raises(ValueError, match="keeps the previous control"):
        buf.push(x[:, 0].astype(np.float32), r[:, 0], z[:, 0])
