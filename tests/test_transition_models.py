"""Issue 13: each plant's one-step model weighed against the window (model.transition_models)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from generalist_control.model.identifier import INPUT_GAIN, TransitionModels, TransitionSet
from generalist_control.model.network import EVIDENCE_WEIGHT, GeneralistNetwork, network_config
from generalist_control.training.setup import model_config
from helpers import compose_cfg
from test_identifier import _window  # windows of order 3 with the previous control

TAG_FREE = dict.fromkeys(
    (
        "integral",
        "linear_skip",
        "tag_free",
        "history_context",
        "control_history",
        "identity_head",
        "infer_tag",
        "transition_identifier",
    ),
    1,
)


def _plants(n_plants: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Random one-step models ``dx = A x + b u + c`` of order 3, padded to 4 states."""
    rng = np.random.default_rng(seed)
    plants = []
    for _ in range(n_plants):
        a, b, c = np.zeros((4, 4)), np.zeros(4), np.zeros(4)
        a[:3, :3] = 0.2 * rng.standard_normal((3, 3))
        b[:3], c[:3] = rng.standard_normal(3), 0.1 * rng.standard_normal(3)
        plants.append((a, b, c))
    return plants


def _transitions(plants, tags: np.ndarray, steps: int, seed: int, noise=0.0, scale=1.0):
    """States, their changes under each window's plant and the controls: (B, T, 4), (B, T)."""
    rng = np.random.default_rng(seed)
    x = scale * rng.standard_normal((len(tags), steps, 4))
    x[..., 3] = 0.0
    u = scale * rng.standard_normal((len(tags), steps))
    dx = np.stack(
        [
            x[i] @ plants[t][0].T + u[i, :, None] * plants[t][1] + plants[t][2]
            for i, t in enumerate(tags)
        ]
    )
    dx[..., :3] += noise * rng.standard_normal(dx[..., :3].shape)
    return tuple(torch.tensor(v, dtype=torch.float32) for v in (x, dx, u))


def _set_models(models: TransitionModels, plants, rows: torch.Tensor) -> None:
    """Parameters whose model for row p is plants[p] exactly (rows: one-hot, so W = theta^T)."""
    theta = np.stack([np.concatenate([a.ravel(), b, c]) for a, b, c in plants])
    with torch.no_grad():
        models.params.weight.zero_()
        models.params.weight[:, : len(plants)] = torch.tensor(theta.T, dtype=torch.float32)
        models.params.bias.zero_()
    assert rows.shape[1] >= len(plants)


def test_evidence_is_half_log_of_each_models_mean_squared_residual():
    """By hand in numpy: -1/2 log(mean_j |dx_j - A_p x_j - b_p u_j - c_p|^2 + eps)."""
    plants = _plants(3, seed=0)
    rows = torch.eye(3, 8)
    models = TransitionModels(state_dim=4, embedding=8)
    _set_models(models, plants, rows)
    tags = np.array([0, 1, 2, 2])
    x, dx, u = _transitions(plants, tags, steps=6, seed=1, noise=0.05)
    got = models(x, dx, u, rows).detach().numpy()
    rss = np.zeros((len(tags), len(plants)))
    for i in range(len(tags)):
        for p, (a, b, c) in enumerate(plants):
            r = dx[i].numpy() - x[i].numpy() @ a.T - u[i].numpy()[:, None] * b - c
            rss[i, p] = (r**2).sum(1).mean()
    np.testing.assert_allclose(got, -0.5 * np.log(rss + models.eps), rtol=1e-4)
    assert (got.argmax(1) == tags).all()  # the plant that made the window explains it best
    with torch.no_grad():
        fit = float(models.fit_loss(models(x, dx, u, rows), torch.tensor(tags)))
    want = np.mean(0.5 * np.log1p(rss[np.arange(len(tags)), tags] / models.eps))
    assert fit == pytest.approx(want, rel=1e-3) and fit > 0


def test_the_true_models_residual_vanishes_where_it_fits_exactly():
    """The moment form in float64: no rounding left where the residual is 0 (eps decides)."""
    plants = _plants(2, seed=5)
    rows = torch.eye(2, 4)
    models = TransitionModels(state_dim=4, embedding=4)
    _set_models(models, plants, rows)
    # states and controls 30x the data's normalised ones: more energy to cancel
    x, dx, u = _transitions(plants, np.array([0, 1]), steps=23, seed=6, scale=30.0)
    residual = models.residual(x, dx, u, rows)
    direct = ((dx.unsqueeze(2) - models.predict(x, u, rows)) ** 2).sum(-1).mean(1)
    torch.testing.assert_close(residual, direct, rtol=1e-4, atol=1e-3)
    assert float(residual[0, 0]) < 1e-3 * models.eps and float(residual[1, 1]) < 1e-3 * models.eps


def test_a_lower_order_model_cannot_explain_a_higher_order_window_by_its_padding():
    """Residuals are taken on every entry: a model predicting 0 in a moving state loses."""
    plants = _plants(1, seed=2)
    truncated = [(a.copy(), b.copy(), c.copy()) for a, b, c in plants]
    for a, b, c in truncated:  # the same plant seen as order 2: its third state padded
        a[2], b[2], c[2] = 0.0, 0.0, 0.0
    rows = torch.eye(2, 4)
    models = TransitionModels(state_dim=4, embedding=4)
    _set_models(models, plants + truncated, rows)
    x, dx, u = _transitions(plants, np.zeros(5, dtype=int), steps=8, seed=3)
    evidence = models(x, dx, u, rows)
    assert (evidence[:, 0] > evidence[:, 1] + 1.0).all()


def test_models_trained_by_their_fit_tell_plants_apart_on_unseen_windows():
    """Learned from transitions alone (rows fixed, zero initial parameters), by fit_loss."""
    torch.manual_seed(0)
    plants = _plants(4, seed=4)
    rows = torch.randn(4, 16)
    models = TransitionModels(state_dim=4, embedding=16)
    assert models.params.weight.abs().max() == 0  # every plant starts with the same evidence
    opt = torch.optim.Adam(models.parameters(), lr=1e-2)
    for step in range(300):
        tags = np.random.default_rng(step).integers(0, 4, 64)
        x, dx, u = _transitions(plants, tags, steps=12, seed=step, noise=0.01)
        loss = models.fit_loss(models(x, dx, u, rows), torch.tensor(tags))
        opt.zero_grad()
        loss.backward()
        opt.step()
    tags = np.random.default_rng(10_000).integers(0, 4, 400)
    x, dx, u = _transitions(plants, tags, steps=12, seed=10_000, noise=0.01)
    named = models(x, dx, u, rows).argmax(1).numpy()
    assert (named == tags).mean() > 0.97


def test_the_network_adds_each_plants_evidence_to_its_identity_logit():
    torch.manual_seed(0)
    net = GeneralistNetwork(**network_config(**TAG_FREE, history=12, transition_models=1))
    assert isinstance(net.identifier, TransitionSet) and net.identifier.models is not None
    state, mask, ref = _window(3, 12)
    tag = torch.tensor([0, 4, 7])
    _, _, code = net.forward_code(state, mask, ref, tag)
    d, n_tags = net.config["hidden"], net.config["n_tags"]
    assert code.shape == (3, d + n_tags)
    evidence = code[:, d:]
    assert torch.allclose(evidence, evidence[:, :1].expand_as(evidence))  # zero models: equal
    torch.nn.init.normal_(net.identifier.models.params.weight, std=0.1)
    _, _, code = net.forward_code(state, mask, ref, tag)
    head = net.identity.weight[:, :d] @ code[:, :d].T + net.identity.bias[:, None]
    torch.testing.assert_close(net.identity_logits(code), head.T + EVIDENCE_WEIGHT * code[:, d:])
    fit = net.transition_fit(code, tag)
    torch.testing.assert_close(fit, net.identifier.models.fit_loss(code[:, d:], tag))
    fit.backward()  # the models' fit never moves the embedding rows the law reads
    assert net.tag_embedding.weight.grad is None or net.tag_embedding.weight.grad.abs().max() == 0
    assert net.identifier.models.params.weight.grad.abs().max() > 0


def test_without_the_models_the_fit_is_zero():
    net = GeneralistNetwork(**network_config(**TAG_FREE, history=12))
    state, mask, ref = _window(2, 12)
    _, _, code = net.forward_code(state, mask, ref, torch.zeros(2, dtype=torch.long))
    assert float(net.transition_fit(code, torch.zeros(2, dtype=torch.long))) == 0.0


@pytest.mark.parametrize("off", ["transition_identifier", "infer_tag"])
def test_the_models_need_the_transition_identifier_and_the_inferred_tag(off):
    with pytest.raises(ValueError, match="model.transition_models weighs each plant"):
        network_config(**{**TAG_FREE, off: 0, "transition_models": 1})


def test_the_models_from_the_config_are_refused_alone():
    with pytest.raises(ValueError, match="set model.transition_identifier=true"):
        model_config(compose_cfg("model.transition_models=true"))


def _scaled(plants, gain: float):
    """The same plants with an actuator delivering ``gain`` times the control."""
    return [(a, gain * b, c) for a, b, c in plants]


@pytest.mark.parametrize(
    ("actuator", "fitted"), [(0.8, 0.8), (1.2, 1.2), (0.5, 0.75), (2.0, 1.25)]
)
def test_the_fitted_input_gain_is_the_least_squares_scale_within_its_range(actuator, fitted):
    """By hand: g = <d, b u> / |b u|^2 of d = dx - A x - c, clipped to INPUT_GAIN; the
    residual at that gain equals numpy's, and the moment form equals the direct form."""
    assert INPUT_GAIN == (0.75, 1.25)
    plants = _plants(3, seed=7)
    rows = torch.eye(3, 8)
    models = TransitionModels(state_dim=4, embedding=8, input_gain=INPUT_GAIN)
    _set_models(models, plants, rows)
    tags = np.array([0, 1, 2])
    x, dx, u = _transitions(_scaled(plants, actuator), tags, steps=9, seed=8, scale=3.0)
    gain = models.gain(x, dx, u, rows).detach().numpy()
    residual = models.residual(x, dx, u, rows).detach().numpy()
    for i in range(len(tags)):
        for p, (a, b, c) in enumerate(plants):
            d = dx[i].numpy() - x[i].numpy() @ a.T - c
            v = u[i].numpy()[:, None] * b
            g = np.clip((d * v).sum() / (v * v).sum(), *INPUT_GAIN)
            assert gain[i, p] == pytest.approx(g, rel=1e-4)
            assert residual[i, p] == pytest.approx(((d - g * v) ** 2).sum(1).mean(), rel=1e-3)
    np.testing.assert_allclose(np.diag(gain), fitted, rtol=1e-4)
    direct = (dx.unsqueeze(2) - models.predict(x, u, rows, models.gain(x, dx, u, rows))) ** 2
    torch.testing.assert_close(
        models.residual(x, dx, u, rows), direct.sum(-1).mean(1), rtol=1e-4, atol=1e-4
    )


def test_an_actuator_off_its_gain_leaves_the_plant_its_evidence():
    """At 80 % actuator gain the true plant's fixed model is off by 0.2 b u; fitted, it
    explains the window to the noise again and names the plant on every window."""
    plants = _plants(6, seed=9)
    rows = torch.eye(6, 8)
    fixed = TransitionModels(state_dim=4, embedding=8)
    fitted = TransitionModels(state_dim=4, embedding=8, input_gain=INPUT_GAIN)
    _set_models(fixed, plants, rows)
    _set_models(fitted, plants, rows)
    tags = np.repeat(np.arange(6), 20)
    x, dx, u = _transitions(_scaled(plants, 0.8), tags, steps=12, seed=10, noise=1e-3)
    true = np.arange(len(tags)), tags
    res_fixed = fixed.residual(x, dx, u, rows).detach().numpy()[true]
    res_fitted = fitted.residual(x, dx, u, rows).detach().numpy()[true]
    assert np.median(res_fitted) < 1e-5 < 1e-2 < np.median(res_fixed)
    assert (fitted(x, dx, u, rows).argmax(1).detach().numpy() == tags).all()


def test_a_window_without_control_leaves_the_gain_at_one():
    plants = _plants(2, seed=11)
    rows = torch.eye(2, 4)
    models = TransitionModels(state_dim=4, embedding=4, input_gain=INPUT_GAIN)
    _set_models(models, plants, rows)
    x, dx, u = _transitions(plants, np.array([0, 1]), steps=6, seed=12)
    u = torch.zeros_like(u)
    assert torch.equal(models.gain(x, dx, u, rows), torch.ones(2, 2))
    fixed = TransitionModels(state_dim=4, embedding=4)
    _set_models(fixed, plants, rows)
    torch.testing.assert_close(models.residual(x, dx, u, rows), fixed.residual(x, dx, u, rows))


def test_the_input_gain_switch_builds_fitted_models_and_needs_them():
    net = GeneralistNetwork(
        **network_config(**TAG_FREE, history=12, transition_models=1, transition_input_gain=1)
    )
    assert net.identifier.models.input_gain == INPUT_GAIN
    plain = GeneralistNetwork(**network_config(**TAG_FREE, history=12, transition_models=1))
    assert plain.identifier.models.input_gain is None
    with pytest.raises(ValueError, match="model.transition_input_gain fits an input gain"):
        network_config(**TAG_FREE, transition_input_gain=1)
    with pytest.raises(ValueError, match="input_gain must hold 1"):
        TransitionModels(state_dim=4, embedding=4, input_gain=(1.1, 2.0))
