"""Issue 13: each plant's one-step model weighed against the window (model.transition_models)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from generalist_control.model.identifier import (
    INPUT_GAIN,
    INPUT_LAGS,
    TransitionModels,
    TransitionSet,
)
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


def _lagged(plants, tags: np.ndarray, steps: int, seed: int, lag: float, offset: float):
    """Windows whose plant sees ``gain (u + lag (u_prev - u)) + offset``: x, dx, u, u_prev."""
    rng = np.random.default_rng(seed)
    u_all = 2.0 * rng.standard_normal((len(tags), steps + 1))
    u, u_prev = u_all[:, 1:], u_all[:, :-1]
    applied = u + lag * (u_prev - u) + offset
    x, dx, _ = _transitions(plants, tags, steps, seed + 1, scale=2.0)
    x_np = x.numpy().astype(float)
    dx = np.stack(
        [
            x_np[i] @ plants[t][0].T + applied[i, :, None] * plants[t][1] + plants[t][2]
            for i, t in enumerate(tags)
        ]
    )
    return x, *(torch.tensor(v, dtype=torch.float32) for v in (dx, u, u_prev))


def _least_squares(x, dx, u, u_prev, plant, lags, gain_range, offset):
    """numpy's least-squares fit of b (g u_a + d) to dx - A x - c, best over the lags.

    The gain is clipped to its range and the offset then refitted: the fit is a convex
    quadratic in (g, d) with d free, so that is its exact minimum over the range.
    """
    a, b, c = plant
    r = dx - x @ a.T - c
    best = (np.inf, 1.0)
    for lag in lags:
        v = u + lag * (u_prev - u)
        cols = [np.outer(v, b).ravel()] + ([np.tile(b, len(v))] if offset else [])
        design = np.stack(cols, 1)
        coef = np.linalg.lstsq(design, r.ravel(), rcond=None)[0]
        g = np.clip(coef[0], *gain_range)
        rest = r.ravel() - g * design[:, 0]
        d = (rest @ design[:, 1]) / (design[:, 1] @ design[:, 1]) if offset else 0.0
        rss = ((rest - d * (design[:, 1] if offset else 0.0)) ** 2).sum() / len(v)
        best = min(best, (rss, g))
    return best


@pytest.mark.parametrize(
    ("lags", "offset"), [(INPUT_LAGS, False), ((0.0,), True), (INPUT_LAGS, True)]
)
def test_the_fitted_lag_and_offset_are_numpys_least_squares(lags, offset):
    """Residual and gain equal numpy's least squares over the lags, the gain clipped."""
    assert INPUT_LAGS == (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
    plants = _plants(3, seed=21)
    rows = torch.eye(3, 8)
    models = TransitionModels(
        state_dim=4, embedding=8, input_gain=INPUT_GAIN, lags=lags, offset=offset
    )
    _set_models(models, plants, rows)
    tags = np.array([0, 1, 2, 0])
    x, dx, u, u_prev = _lagged(_scaled(plants, 1.4), tags, steps=10, seed=22, lag=0.35,
                               offset=0.5)  # fmt: skip
    residual = models.residual(x, dx, u, rows, u_prev).detach().numpy()
    gain = models.gain(x, dx, u, rows, u_prev).detach().numpy()
    for i in range(len(tags)):
        for p, plant in enumerate(plants):
            args = (x[i].numpy(), dx[i].numpy(), u[i].numpy(), u_prev[i].numpy(), plant)
            rss, g = _least_squares(*args, lags, INPUT_GAIN, offset)
            assert residual[i, p] == pytest.approx(rss, rel=1e-3, abs=1e-5)
            assert gain[i, p] == pytest.approx(g, rel=1e-4)


def test_a_lagged_biased_actuator_leaves_the_plant_its_evidence():
    """A 0.4 lag and a constant input disturbance: the fixed models name the wrong plant
    on some windows; with the lag and offset fitted the true model explains every window
    (to the noise) and is named on each."""
    plants = _plants(6, seed=23)
    rows = torch.eye(6, 8)
    fixed = TransitionModels(state_dim=4, embedding=8, input_gain=INPUT_GAIN)
    fitted = TransitionModels(
        state_dim=4, embedding=8, input_gain=INPUT_GAIN, lags=INPUT_LAGS, offset=True
    )
    _set_models(fixed, plants, rows)
    _set_models(fitted, plants, rows)
    tags = np.repeat(np.arange(6), 20)
    x, dx, u, u_prev = _lagged(plants, tags, steps=12, seed=24, lag=0.4, offset=0.8)
    true = np.arange(len(tags)), tags
    res_fixed = fixed.residual(x, dx, u, rows).detach().numpy()[true]
    res_fitted = fitted.residual(x, dx, u, rows, u_prev).detach().numpy()[true]
    assert np.median(res_fitted) < 1e-6 < 1e-1 < np.median(res_fixed)
    assert (fitted(x, dx, u, rows, u_prev).argmax(1).detach().numpy() == tags).all()
    with pytest.raises(ValueError, match="needs u_prev"):
        fitted.residual(x, dx, u, rows)


def test_without_lag_or_offset_the_evidence_is_unchanged():
    """The switches off: the same residual as the models before them (no lag, no offset)."""
    plants = _plants(3, seed=25)
    rows = torch.eye(3, 8)
    base = TransitionModels(state_dim=4, embedding=8, input_gain=INPUT_GAIN)
    explicit = TransitionModels(
        state_dim=4, embedding=8, input_gain=INPUT_GAIN, lags=(0.0,), offset=False
    )
    _set_models(base, plants, rows)
    _set_models(explicit, plants, rows)
    x, dx, u, u_prev = _lagged(plants, np.array([0, 1, 2]), steps=8, seed=26, lag=0.2,
                               offset=0.1)  # fmt: skip
    torch.testing.assert_close(
        base.residual(x, dx, u, rows), explicit.residual(x, dx, u, rows, u_prev)
    )
    with pytest.raises(ValueError, match="lags must be"):
        TransitionModels(state_dim=4, embedding=4, lags=(0.0, 1.5))


def test_the_lag_and_offset_switches_build_fitted_models_and_need_them():
    cfg = network_config(
        **TAG_FREE, history=12, transition_models=1, transition_input_lag=1,
        transition_input_offset=1,
    )  # fmt: skip
    models = GeneralistNetwork(**cfg).identifier.models
    assert models.lags == INPUT_LAGS and models.offset and models.input_gain is None
    with pytest.raises(ValueError, match="model.transition_input_lag fits an input lag"):
        network_config(**TAG_FREE, transition_input_lag=1)
    with pytest.raises(ValueError, match="model.transition_input_offset fits an input offset"):
        network_config(**TAG_FREE, transition_input_offset=1)


def test_identity_noise_reaches_only_the_identifier_and_only_in_training():
    """In training mode the identifier reads the window with noise on its unpadded plant
    states only (integral and control channels, padding untouched), its std per window
    at most identity_noise; in eval mode (run time) the output is the noise-free one."""
    cfg = network_config(**TAG_FREE, history=12, transition_models=1, law_history=8)
    torch.manual_seed(0)
    net = GeneralistNetwork(**cfg)
    state, mask, ref = _window(batch=64, history=12)
    tag = torch.zeros(64, dtype=torch.long)
    seen: list[torch.Tensor] = []
    forward = net.identifier.forward
    net.identifier.forward = lambda s, m, rows=None: seen.append(s) or forward(s, m, rows)
    net.eval()
    clean = net(state, mask, ref, tag)[0]
    net.identity_noise = 0.5
    torch.testing.assert_close(net(state, mask, ref, tag)[0], clean)
    assert torch.equal(seen[-1], state)
    net.train()
    net(state, mask, ref, tag)
    noise = seen[-1] - state
    assert torch.equal(noise[..., 3:], torch.zeros_like(noise[..., 3:]))  # padding, z, u
    std = noise[..., :3].std(dim=(1, 2))
    assert 0.0 < std.min() < 0.1 and 0.4 < std.max() < 0.6 and 0.15 < std.mean() < 0.35


def test_identity_noise_in_the_config_is_checked():
    from generalist_control.training.setup import identity_noise

    on = compose_cfg("experiment=tag_free", "model.identity_noise=0.02")
    assert identity_noise(on) == 0.02
    with pytest.raises(ValueError, match="model.identity_noise"):
        identity_noise(compose_cfg("model.identity_noise=-1"))
    with pytest.raises(ValueError, match="set model.control_history=true"):
        identity_noise(compose_cfg("model.identity_noise=0.1"))


def _trajectory_windows(plants, tags: np.ndarray, history: int, seed: int):
    """Windows (B, history, 5) of each tag's plant driven by random controls, and masks.

    ``x_(j+1) = x_j + A x_j + b u_j + c`` from a random start; the last channel is the
    previous control (sample j + 1 holds ``u_j``), the order 3, the fourth state padding.
    """
    rng = np.random.default_rng(seed)
    state = np.zeros((len(tags), history, 5))
    x = rng.standard_normal((len(tags), 4))
    x[:, 3] = 0.0
    a, b, c = (np.stack([plants[t][k] for t in tags]) for k in range(3))
    for j in range(history):
        u = rng.standard_normal(len(tags))
        state[:, j, :4] = x
        if j + 1 < history:
            state[:, j + 1, 4] = u
        x = x + np.einsum("bij,bj->bi", a, x) + u[:, None] * b + c
    mask = np.zeros_like(state)
    mask[..., :3] = mask[..., 4] = 1.0
    return torch.tensor(state, dtype=torch.float32), torch.tensor(mask, dtype=torch.float32)


def _stable_plants(n_plants: int, seed: int):
    """Order-3 one-step models near ``-0.3 I`` (stable over a window), padded to 4 states."""
    plants = []
    for a, b, c in _plants(n_plants, seed):
        a[:3, :3] = -0.3 * np.eye(3) + 0.5 * a[:3, :3]
        plants.append((a, b, c))
    return plants


def test_with_clean_fit_the_models_fit_the_clean_windows_and_stay_unbiased():
    """Fitted to noisy windows, least squares with noise in its regressors biases the
    models (errors in variables): noise ``n_j`` on ``x_j`` enters ``x_(j+1) - x_j`` as
    ``-n_j``, so the diagonal of ``A`` shrinks towards -1. With ``clean_fit``
    :meth:`TransitionSet.read` fits them to the clean windows and recovers each plant's
    one-step model to 3e-3; without it the same training misses by more than 2e-2
    (4.2e-2 to 6.9e-2 measured over 4 seeds), the diagonal lower by more than 1e-2."""
    plants = _stable_plants(3, seed=0)
    tags = np.repeat(np.arange(3), 32)
    state, mask = _trajectory_windows(plants, tags, history=12, seed=1)
    tag, rows = torch.tensor(tags), torch.eye(3, 8)
    truth = torch.tensor(np.stack([np.concatenate([a.ravel(), b, c]) for a, b, c in plants]))
    seen = [4 * i + j for i in range(3) for j in range(3)] + [16, 17, 18, 20, 21, 22]
    errors, shrink = {}, {}
    for fitted_to in ("clean", "noisy"):
        torch.manual_seed(0)
        ident = TransitionSet(4, 8, TransitionModels(4, 8))
        opt = torch.optim.Adam(ident.parameters(), lr=0.02)
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, 0.99)
        for _ in range(300):
            code, fit = ident.read(state, mask, rows, 1.0, clean_fit=fitted_to == "clean")
            if fitted_to == "noisy":  # the fit reads the evidence the head reads
                assert fit is None
                fit = code[:, -3:]
            loss = ident.models.fit_loss(fit, tag)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        error = ident.models.params(rows).detach().double() - truth
        errors[fitted_to] = float(error[:, seen].abs().max())
        shrink[fitted_to] = float(error[:, [0, 5, 10]].mean())  # A's diagonal
    assert errors["clean"] < 3e-3 and abs(shrink["clean"]) < 1e-3
    assert errors["noisy"] > 2e-2 and shrink["noisy"] < -1e-2


def test_with_clean_fit_the_head_reads_noisy_evidence_and_the_fit_clean():
    """In training with identity noise and ``identity_clean_fit`` the network's fit
    evidence is the models' evidence on the clean window (recomputed here), the evidence
    the head reads is another (the noisy window's) and passes the models no gradient;
    without the switch, without noise or in eval mode the fit reads the head's evidence
    (``fit_evidence`` None), and under noise the head's loss reaches the models."""
    cfg = network_config(**TAG_FREE, history=12, transition_models=1, law_history=8)
    torch.manual_seed(0)
    net = GeneralistNetwork(**cfg)
    with torch.no_grad():
        net.identifier.models.params.weight.normal_(0.0, 0.1)
    state, mask, ref = _window(batch=16, history=12)
    tag = torch.arange(16) % cfg["n_tags"]
    rows = net.tag_embedding.weight[: cfg["n_tags"]].detach()
    net.train()
    net.identity_noise, net.identity_clean_fit = 0.1, True
    _, _, code = net.forward_code(state, mask, ref, tag)
    clean = net.identifier.evidence(state, mask, rows)
    torch.testing.assert_close(net.fit_evidence, clean)
    assert not torch.allclose(code[:, -cfg["n_tags"] :], clean)
    net.identity_logits(code).logsumexp(1).sum().backward()
    grad = net.identifier.models.params.weight.grad
    assert grad is None or torch.count_nonzero(grad) == 0
    net.zero_grad()
    net.transition_fit(code, tag).backward()
    assert torch.count_nonzero(net.identifier.models.params.weight.grad) > 0
    for training, noise in ((True, 0.0), (False, 0.1)):
        net.train(training)
        net.identity_noise = noise
        _, _, code = net.forward_code(state, mask, ref, tag)
        assert net.fit_evidence is None
        evidence = code[:, -cfg["n_tags"] :]
        torch.testing.assert_close(evidence, net.identifier.evidence(state, mask, rows))
    net.train()
    net.identity_noise, net.identity_clean_fit = 0.1, False
    net.zero_grad()
    _, _, code = net.forward_code(state, mask, ref, tag)
    assert net.fit_evidence is None
    assert not torch.allclose(code[:, -cfg["n_tags"] :], clean)  # the noisy window's
    net.identity_logits(code).logsumexp(1).sum().backward()
    assert torch.count_nonzero(net.identifier.models.params.weight.grad) > 0


def test_the_clean_fit_switch_is_checked():
    from generalist_control.training.setup import identity_clean_fit

    noisy = ("experiment=tag_free", "model.identity_noise=0.02")
    assert identity_clean_fit(compose_cfg(*noisy, "model.identity_noise_clean_fit=true"))
    assert not identity_clean_fit(compose_cfg(*noisy))
    for bad in (
        ("experiment=tag_free", "model.identity_noise=0"),
        (*noisy, "model.transition_models=false", "model.transition_input_gain=false"),
    ):
        with pytest.raises(ValueError, match="needs model.identity_noise > 0 and model.transi"):
            identity_clean_fit(compose_cfg(*bad, "model.identity_noise_clean_fit=true"))
