"""Each plant's one-step model weighed against the window (an inferred plant's ``models``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from generalist_control.model.identifier import TransitionModels, TransitionSet
from generalist_control.model.plant import EVIDENCE_WEIGHT
from helpers import build_net, compose_cfg
from test_identifier import _window  # windows of order 3 with the previous control

#: The actuator gain range and the lags the tag-free recipe fits (conf/model/plant/inferred).
INPUT_GAIN = (0.75, 1.25)
INPUT_LAGS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)


def _inferred(**models):
    """A tag-free network (history 12) whose identifier has one-step models ``models``."""
    return build_net(channels=["integral", "previous_control"], skip="context", history=12,
                     plant="inferred", models=models)  # fmt: skip


def test_the_tag_free_recipe_fits_that_range_and_those_lags():
    from omegaconf import OmegaConf

    cfg = compose_cfg("experiment=tag_free")
    models = OmegaConf.to_container(cfg.model.plant.identifier.models)
    assert tuple(models["input_gain"]) == INPUT_GAIN and tuple(models["lags"]) == INPUT_LAGS
    assert models["offset"] is True and cfg.model.plant.noise == 0.02


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


def _predict(models: TransitionModels, x, u, rows, gain=None) -> torch.Tensor:
    """The direct form: each plant's predicted change (B, T, plants, 4), ``b_p`` times ``gain``."""
    z = torch.cat([x, u.unsqueeze(-1), torch.ones_like(u).unsqueeze(-1)], dim=-1)
    theta = models.theta(rows)
    change = torch.einsum("pik,btk->btpi", theta, z)
    if gain is None:
        return change
    return change + torch.einsum("bp,pi,bt->btpi", gain - 1.0, theta[:, :, 4], u)


def test_the_true_models_residual_vanishes_where_it_fits_exactly():
    """The moment form in float64: no rounding left where the residual is 0 (eps decides)."""
    plants = _plants(2, seed=5)
    rows = torch.eye(2, 4)
    models = TransitionModels(state_dim=4, embedding=4)
    _set_models(models, plants, rows)
    # states and controls 30x the data's normalised ones: more energy to cancel
    x, dx, u = _transitions(plants, np.array([0, 1]), steps=23, seed=6, scale=30.0)
    residual = models.fit(x, dx, u, rows)[0]
    direct = ((dx.unsqueeze(2) - _predict(models, x, u, rows)) ** 2).sum(-1).mean(1)
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
    net = _inferred()
    plant = net.plant
    assert isinstance(plant.identifier, TransitionSet) and plant.identifier.models is not None
    state, mask, ref = _window(3, 12)
    tag = torch.tensor([0, 4, 7])
    reading = net(state, mask, ref, tag).plant
    d, n_tags = 32, plant.n_tags
    assert reading.summary.shape == (3, d + n_tags) and reading.evidence.shape == (3, n_tags)
    evidence = reading.evidence
    assert torch.allclose(evidence, evidence[:, :1].expand_as(evidence))  # zero models: equal
    torch.nn.init.normal_(plant.identifier.models.params.weight, std=0.1)
    reading = net(state, mask, ref, tag).plant
    code = reading.summary
    head = plant.head.weight[:, :d] @ code[:, :d].T + plant.head.bias[:, None]
    torch.testing.assert_close(reading.logits, head.T + EVIDENCE_WEIGHT * code[:, d:])
    cross_entropy, identity = plant.loss(reading, tag)
    fit = identity - cross_entropy
    torch.testing.assert_close(fit, plant.identifier.models.fit_loss(code[:, d:], tag))
    net.zero_grad()
    plant.identifier.models.fit_loss(reading.evidence, tag).backward()
    # the models' fit never moves the embedding rows the law reads
    assert plant.rows.weight.grad is None or plant.rows.weight.grad.abs().max() == 0
    assert plant.identifier.models.params.weight.grad.abs().max() > 0


def test_without_the_models_the_identity_term_is_the_cross_entropy():
    net = build_net(channels=["integral", "previous_control"], history=12, plant="inferred",
                    models=None)  # fmt: skip
    state, mask, ref = _window(2, 12)
    tag = torch.zeros(2, dtype=torch.long)
    reading = net(state, mask, ref, tag).plant
    assert reading.evidence is None
    cross_entropy, identity = net.plant.loss(reading, tag)
    assert torch.equal(cross_entropy, identity)
    torch.testing.assert_close(
        cross_entropy, torch.nn.functional.cross_entropy(reading.logits, tag)
    )


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
    gain = models.fit(x, dx, u, rows)[1].detach().numpy()
    residual = models.fit(x, dx, u, rows)[0].detach().numpy()
    for i in range(len(tags)):
        for p, (a, b, c) in enumerate(plants):
            d = dx[i].numpy() - x[i].numpy() @ a.T - c
            v = u[i].numpy()[:, None] * b
            g = np.clip((d * v).sum() / (v * v).sum(), *INPUT_GAIN)
            assert gain[i, p] == pytest.approx(g, rel=1e-4)
            assert residual[i, p] == pytest.approx(((d - g * v) ** 2).sum(1).mean(), rel=1e-3)
    np.testing.assert_allclose(np.diag(gain), fitted, rtol=1e-4)
    direct = (dx.unsqueeze(2) - _predict(models, x, u, rows, models.fit(x, dx, u, rows)[1])) ** 2
    torch.testing.assert_close(
        models.fit(x, dx, u, rows)[0], direct.sum(-1).mean(1), rtol=1e-4, atol=1e-4
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
    res_fixed = fixed.fit(x, dx, u, rows)[0].detach().numpy()[true]
    res_fitted = fitted.fit(x, dx, u, rows)[0].detach().numpy()[true]
    assert np.median(res_fitted) < 1e-5 < 1e-2 < np.median(res_fixed)
    assert (fitted(x, dx, u, rows).argmax(1).detach().numpy() == tags).all()


def test_a_window_without_control_leaves_the_gain_at_one():
    plants = _plants(2, seed=11)
    rows = torch.eye(2, 4)
    models = TransitionModels(state_dim=4, embedding=4, input_gain=INPUT_GAIN)
    _set_models(models, plants, rows)
    x, dx, u = _transitions(plants, np.array([0, 1]), steps=6, seed=12)
    u = torch.zeros_like(u)
    assert torch.equal(models.fit(x, dx, u, rows)[1], torch.ones(2, 2))
    fixed = TransitionModels(state_dim=4, embedding=4)
    _set_models(fixed, plants, rows)
    torch.testing.assert_close(models.fit(x, dx, u, rows)[0], fixed.fit(x, dx, u, rows)[0])


def test_the_models_config_builds_fitted_models_and_refuses_a_bad_range():
    assert _inferred(input_gain=list(INPUT_GAIN)).plant.identifier.models.input_gain == INPUT_GAIN
    assert _inferred().plant.identifier.models.input_gain is None
    with pytest.raises(ValueError, match=r"input_gain must be a range \[low, high\]"):
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
    residual = models.fit(x, dx, u, rows, u_prev)[0].detach().numpy()
    gain = models.fit(x, dx, u, rows, u_prev)[1].detach().numpy()
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
    res_fixed = fixed.fit(x, dx, u, rows)[0].detach().numpy()[true]
    res_fitted = fitted.fit(x, dx, u, rows, u_prev)[0].detach().numpy()[true]
    assert np.median(res_fitted) < 1e-6 < 1e-1 < np.median(res_fixed)
    assert (fitted(x, dx, u, rows, u_prev).argmax(1).detach().numpy() == tags).all()
    with pytest.raises(ValueError, match="needs u_prev"):
        fitted.fit(x, dx, u, rows)[0]


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
        base.fit(x, dx, u, rows)[0], explicit.fit(x, dx, u, rows, u_prev)[0]
    )
    with pytest.raises(ValueError, match="lags must be"):
        TransitionModels(state_dim=4, embedding=4, lags=(0.0, 1.5))


def test_the_lag_and_offset_settings_build_fitted_models():
    models = _inferred(lags=list(INPUT_LAGS), offset=True).plant.identifier.models
    assert models.lags == INPUT_LAGS and models.offset and models.input_gain is None


def test_identity_noise_reaches_only_the_identifier_and_only_in_training():
    """In training mode the identifier reads the window with noise on its unpadded plant
    states only (integral and control channels, padding untouched), its std per window
    at most the plant part's noise; in eval mode (run time) the output is the noise-free one."""
    torch.manual_seed(0)
    quiet = build_net(channels=["integral", "previous_control"], skip="context", history=12,
                      law_history=8, plant="inferred")  # fmt: skip
    net = build_net(channels=["integral", "previous_control"], skip="context", history=12,
                    law_history=8, plant="inferred", noise=0.5)  # fmt: skip
    net.load_state_dict(quiet.state_dict())
    state, mask, ref = _window(batch=64, history=12)
    tag = torch.zeros(64, dtype=torch.long)
    seen: list[torch.Tensor] = []
    identifier = net.plant.identifier
    forward = identifier.forward
    identifier.forward = lambda s, m, rows=None: seen.append(s) or forward(s, m, rows)
    net.eval()
    quiet.eval()
    clean = quiet(state, mask, ref, tag).control
    torch.testing.assert_close(net(state, mask, ref, tag).control, clean)
    assert torch.equal(seen[-1], state)
    net.train()
    net(state, mask, ref, tag)
    noise = seen[-1] - state
    assert torch.equal(noise[..., 3:], torch.zeros_like(noise[..., 3:]))  # padding, z, u
    std = noise[..., :3].std(dim=(1, 2))
    assert 0.0 < std.min() < 0.1 and 0.4 < std.max() < 0.7 and 0.15 < std.mean() < 0.35


def test_the_plant_part_s_noise_is_checked():
    with pytest.raises(ValueError, match="model.plant.noise must be a finite number >= 0"):
        build_net(channels=["previous_control"], plant="inferred", noise=-1.0)


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
