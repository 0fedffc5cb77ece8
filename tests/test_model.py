"""The network, the normaliser, the policy file and the data split, on tiny data."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from generalist_control.datamodule import BatchIndexSampler, split_by_trajectory
from generalist_control.model import GeneralistController, controller_config, count_parameters
from generalist_control.normalise import Normaliser
from generalist_control.policy import FlatPolicy, Policy, load_policy, save_policy


def _tensors(windows):
    return [
        torch.from_numpy(np.asarray(a))
        for a in (windows.state, windows.mask, windows.ref, windows.tag)
    ]


@pytest.fixture(scope="module")
def windows(tiny_demos):
    return tiny_demos.windows(8, 3)


@pytest.fixture(scope="module")
def policy(windows):
    torch.manual_seed(0)
    pol = Policy(controller_config(hidden=16, experts=3))
    pol.normaliser.fit(*_tensors(windows)[:4], torch.from_numpy(windows.target))
    return pol.eval()


@pytest.mark.parametrize(("hidden", "experts", "heads"), [(16, 1, 3), (32, 3, 3), (64, 5, 4)])
def test_output_shapes(hidden, experts, heads):
    net = GeneralistController(hidden=hidden, experts=experts, heads=heads)
    B = 7
    u, gates = net(
        torch.randn(B, 8, 4), torch.ones(B, 8, 4), torch.randn(B, 8), torch.randint(0, 25, (B,))
    )
    assert u.shape == (B, 3)
    assert gates.shape == (B, experts)


def test_gate_weights_sum_to_one(policy, windows):
    u, gates = policy.predict_windows(windows)
    assert np.all(gates >= 0)
    np.testing.assert_allclose(gates.sum(axis=1), 1.0, rtol=1e-6)
    assert u.shape == (len(windows), 3)


def test_padded_state_entries_do_not_change_the_output(policy, windows):
    state, mask, ref, tag = _tensors(windows)
    assert (mask == 0).any(), "the tiny set must hold a plant of order < 4"
    noisy = state + 1e3 * torch.randn_like(state) * (1 - mask)  # garbage in padded entries only
    with torch.no_grad():
        u0, g0 = policy(state, mask, ref, tag)
        u1, g1 = policy(noisy, mask, ref, tag)
        n0, _ = policy.net(state, mask, ref, tag)
        n1, _ = policy.net(noisy, mask, ref, tag)
    torch.testing.assert_close(u1, u0, rtol=0, atol=0)
    torch.testing.assert_close(g1, g0, rtol=0, atol=0)
    torch.testing.assert_close(n1, n0, rtol=0, atol=0)  # the network masks on its own too


def test_slow_lstm_ends_at_the_newest_sample():
    for history, stride in [(8, 2), (8, 3), (8, 1), (5, 4)]:
        net = GeneralistController(history=history, stride=stride)
        idx = list(range(history))[net.slow_start :: stride]
        assert idx[-1] == history - 1 and idx[1:] == [i + stride for i in idx[:-1]]


def test_heads_that_do_not_divide_the_width():
    net = GeneralistController(hidden=32, heads=3)  # 2 d_h = 64, d_k = ceil(64 / 3) = 22
    assert net.attention.d_k == 22
    assert net.attention.out.in_features == 66 and net.attention.out.out_features == 64


def test_attention_over_one_token_leaves_query_and_key_without_gradient():
    # docs/training.md: the paper's attention runs over the single vector z
    net = GeneralistController(hidden=16, heads=3)
    u, _ = net(torch.randn(4, 8, 4), torch.ones(4, 8, 4), torch.randn(4, 8), torch.arange(4))
    u.sum().backward()
    inner = net.attention.heads * net.attention.d_k
    grad = net.attention.qkv.weight.grad
    # zero up to rounding in the softmax backward
    assert grad[: 2 * inner].abs().max() < 1e-6 * grad[2 * inner :].abs().max()


def test_parameter_count_of_the_baseline_matches_docs():
    # docs/training.md, table "Parameter counts"
    assert count_parameters(GeneralistController(hidden=32, experts=3)) == 55_826
    assert count_parameters(GeneralistController(hidden=64, experts=3)) == 215_567
    ours = {"linear_head": 1, "integral": 1, "linear_samples": 1}  # conf/model/generalist.yaml
    assert count_parameters(GeneralistController(hidden=32, experts=3, **ours)) == 56_340


def test_integral_adds_one_state_channel_that_padding_never_reaches(tiny_demos):
    """model.integral: one more encoder input (+ the linear head's), masks still hold."""
    base = count_parameters(GeneralistController(hidden=32, experts=3, linear_head=1))
    with_z = count_parameters(
        GeneralistController(hidden=32, experts=3, linear_head=1, integral=1)
    )
    # two state encoders gain a d-wide input column each; the head gains T * K weights per tag
    assert with_z - base == 2 * 32 + 25 * 8 * 3
    windows = tiny_demos.windows(8, 3, integral=True)
    torch.manual_seed(0)
    pol = Policy(controller_config(hidden=16, experts=3, window_scale=1, integral=1))
    pol.normaliser.fit(*_tensors(windows)[:4], torch.from_numpy(windows.target))
    assert pol.normaliser.state_scale.shape == (25, 5)
    state, mask, ref, tag = _tensors(windows)
    assert (mask[..., :4] == 0).any() and (mask[..., 4] == 1).all()
    noisy = state + 1e3 * torch.randn_like(state) * (1 - mask)
    with torch.no_grad():
        torch.testing.assert_close(pol(noisy, mask, ref, tag), pol(state, mask, ref, tag))
        moved = state.clone()
        moved[..., 4] += 1.0  # the integral is seen
        assert not torch.allclose(pol(moved, mask, ref, tag)[0], pol(state, mask, ref, tag)[0])


def test_least_squares_head_recovers_the_lqi_law_from_the_data(tiny_demos):
    """linear_init=lstsq: from the demonstrations alone, the head's first control is
    -Kx x - Ki z of each plant's LQI design, at any augmented state (not only on the data)."""
    from generalist_control.catalog import load_plant
    from generalist_control.lqi import design_lqi

    windows = tiny_demos.windows(8, 3, integral=True)
    cfg = controller_config(hidden=16, experts=2, window_scale=1, linear_head=1, integral=1,
                            linear_samples=1)  # fmt: skip
    torch.manual_seed(0)
    pol = Policy(cfg)
    tensors = dict(zip(("state", "mask", "ref", "tag"), _tensors(windows), strict=True))
    tensors["target"] = torch.from_numpy(windows.target)
    pol.normaliser.fit(**tensors)
    residuals = pol.fit_linear_head(**tensors)
    assert set(residuals) == {load_plant(n).tag for n in ("cstr", "hydraulic_actuator")}
    assert max(residuals.values()) < 1e-4  # linear plants: the whole plan is linear
    rng = np.random.default_rng(0)
    for name in ("cstr", "hydraulic_actuator"):
        plant = load_plant(name)
        g = design_lqi(plant)
        x = np.zeros((50, 8, 5), np.float32)
        x[:, :, : plant.order] = rng.normal(size=(50, 8, plant.order))
        x[:, :, 4] = rng.normal(size=(50, 8))
        mask = np.zeros_like(x)
        mask[:, :, : plant.order] = 1.0
        mask[:, :, 4] = 1.0
        r = rng.normal(size=(50, 8)).astype(np.float32)
        tag = torch.full((50,), plant.tag)
        with torch.no_grad():
            u, _ = pol(torch.from_numpy(x), torch.from_numpy(mask), torch.from_numpy(r), tag)
        law = -(x[:, -1, : plant.order].astype(float) @ g.Kx) - g.Ki * x[:, -1, 4]
        np.testing.assert_allclose(u[:, 0].numpy(), law, rtol=1e-3, atol=1e-3 * np.abs(law).max())
    with pytest.raises(ValueError, match="no linear head"):
        Policy(controller_config(hidden=16)).fit_linear_head(**tensors)


def test_model_config_is_checked():
    with pytest.raises(ValueError, match=r"linear_samples \(9\) exceeds the history \(8\)"):
        controller_config(linear_samples=9)
    with pytest.raises(ValueError, match="unknown model config keys"):
        controller_config(hiden=32)
    with pytest.raises(ValueError, match="must be even"):
        controller_config(hidden=33)


def test_normalisation_round_trips(policy, windows):
    norm = policy.normaliser
    state, mask, ref, tag = _tensors(windows)
    u = torch.from_numpy(windows.target)
    torch.testing.assert_close(norm.denormalise_controls(norm.normalise_controls(u, tag), tag), u)
    xs, ms, rs, _ = norm.normalise_inputs(state, mask, ref, tag)
    torch.testing.assert_close(xs * norm.state_scale[tag].unsqueeze(1), state * mask)
    torch.testing.assert_close(rs * norm.ref_scale[tag].unsqueeze(1), ref)
    assert torch.all(xs[mask == 0] == 0)
    # per tag, every real state entry, the reference and the controls have unit RMS
    un = norm.normalise_controls(u, tag)
    for t in tag.unique():
        sel = tag == t
        order = int(mask[sel][0, 0].sum())
        rms_x = xs[sel][..., :order].pow(2).mean(dim=(0, 1)).sqrt()
        torch.testing.assert_close(rms_x, torch.ones(order), rtol=1e-4, atol=0)
        torch.testing.assert_close(rs[sel].pow(2).mean().sqrt(), torch.tensor(1.0))
        torch.testing.assert_close(un[sel].pow(2).mean().sqrt(), torch.tensor(1.0))
    assert norm.seen.sum() == 2
    assert torch.all(norm.control_scale[~norm.seen] > 0)


def test_normaliser_rejects_out_of_range_tags():
    norm = Normaliser(n_tags=4, state_dim=4)
    with pytest.raises(ValueError, match="system tags must lie in 0..3"):
        norm.fit(
            torch.ones(2, 8, 4),
            torch.ones(2, 8, 4),
            torch.ones(2, 8),
            torch.tensor([0, 7]),
            torch.ones(2, 3),
        )


def test_policy_file_round_trips_with_weights_only(policy, windows, tmp_path):
    meta = {"tags": {"cstr": 10, "hydraulic_actuator": 13}, "dt": 0.05, "content_hash": "x"}
    path = save_policy(tmp_path / "policy.ckpt", policy, meta)
    torch.load(path, weights_only=True)  # plain types and tensors only
    loaded, loaded_meta = load_policy(path)
    assert loaded_meta == meta
    u0, g0 = policy.predict_windows(windows)
    u1, g1 = loaded.predict_windows(windows)
    np.testing.assert_array_equal(u1, u0)
    np.testing.assert_array_equal(g1, g0)


def test_flat_policy_matches_policy(policy, windows):
    n = len(windows)
    x = np.concatenate(
        [
            windows.state.reshape(n, -1),
            windows.mask.reshape(n, -1),
            windows.ref,
            windows.tag[:, None],
        ],
        axis=1,
    ).astype(np.float32)
    with torch.no_grad():
        u_flat = FlatPolicy(policy)(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(u_flat, policy.predict_windows(windows)[0], rtol=1e-6)


def test_split_is_by_trajectory_and_covers_every_plant(tiny_demos):
    is_val = split_by_trajectory(tiny_demos.plant, 0.1, seed=0)
    w = tiny_demos.windows(8, 3)
    val_traj, train_traj = set(w.traj[is_val[w.traj]]), set(w.traj[~is_val[w.traj]])
    assert val_traj and train_traj and not val_traj & train_traj
    assert set(tiny_demos.plant[is_val]) == set(tiny_demos.plant)
    np.testing.assert_array_equal(is_val, split_by_trajectory(tiny_demos.plant, 0.1, seed=0))


def test_batch_sampler_reshuffles_per_epoch_and_covers_all():
    s = BatchIndexSampler(10, 4, shuffle=True, seed=1)
    first = torch.cat(list(s))
    assert len(s) == 3 and sorted(first.tolist()) == list(range(10))
    s.set_epoch(1)
    second = torch.cat(list(s))
    assert not torch.equal(first, second)
    s.set_epoch(0)
    assert torch.equal(torch.cat(list(s)), first)


def test_linear_head_adds_a_per_tag_linear_map_of_the_window(windows):
    """Zero at start (the paper's network); then exactly W[tag] @ [state*mask, ref]."""
    torch.manual_seed(0)
    base = GeneralistController(**controller_config(hidden=8))
    torch.manual_seed(0)
    head = GeneralistController(**controller_config(hidden=8, linear_head=1))
    args = [
        torch.as_tensor(np.asarray(a))
        for a in (windows.state, windows.mask, windows.ref, windows.tag)
    ]
    u0, _ = base(*args)
    u1, _ = head(*args)
    torch.testing.assert_close(u1, u0)
    with torch.no_grad():
        head.linear.weight.normal_()
    u2, _ = head(*args)
    state, mask, ref, tag = args
    window = torch.cat([(state * mask).flatten(1), ref], dim=1)
    w = head.linear.weight[tag].view(len(tag), 3, -1)
    torch.testing.assert_close(
        u2 - u0, torch.einsum("bkf,bf->bk", w, window), rtol=1e-4, atol=1e-4
    )
    with pytest.raises(ValueError, match="linear_head must be 0 or 1"):
        controller_config(linear_head=2)
