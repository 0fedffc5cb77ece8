"""Without the tag (experiment=tag_free): the plant inferred from the window by its own part."""

from __future__ import annotations

import math

import pytest
import torch

from generalist_control.common.sections import as_dict
from generalist_control.model.identifier import TransitionSet
from generalist_control.model.plant import InferredPlant
from generalist_control.model.policy import Policy
from generalist_control.training.lit_module import ImitationModule
from generalist_control.training.settings import read_training
from helpers import compose_cfg, net_config

OPT = {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": 1e-2}
CHANNELS = ["integral", "previous_control"]


def _inferred(**kw):
    """A tag-free network (8-sample window, no one-step models unless given)."""
    kw.setdefault("models", None)
    return net_config(channels=CHANNELS, skip="context", plant="inferred", **kw)


def _batch(n: int = 64, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "state": torch.randn(n, 8, 6, generator=g),
        "mask": torch.ones(n, 8, 6),
        "ref": torch.randn(n, 8, generator=g),
        "tag": torch.randint(0, 25, (n,), generator=g),
        "target": torch.randn(n, 3, generator=g),
    }


def test_experiment_tag_free_composes_the_inferred_plant():
    settings = read_training(as_dict(compose_cfg("experiment=tag_free")))
    policy = Policy(settings.model)
    assert isinstance(policy.net.plant, InferredPlant)
    assert isinstance(policy.net.plant.identifier, TransitionSet)
    assert policy.channels == ("integral", "previous_control")
    assert (policy.history, policy.net.law_history) == (24, 8)
    sampler = settings.dagger.sampler  # type: ignore[union-attr]
    assert sampler.actuator is not None and (sampler.actuator.lag, sampler.actuator.offset) == (
        1.0,
        0.3,
    )
    assert Policy(read_training(as_dict(compose_cfg())).model).channels == ("integral",)


def test_an_inferred_plant_weighs_the_rows_by_its_head_and_ignores_the_tag():
    torch.manual_seed(0)
    net = Policy(_inferred()).net.eval()
    torch.nn.init.normal_(net.skip.gains.weight)  # zero at initialisation: give it gains
    batch = _batch(n=6)
    state, mask, ref = batch["state"], batch["mask"], batch["ref"]
    tags_a, tags_b = torch.arange(6), torch.arange(6).flip(0) + 10
    plant = net.plant
    with torch.no_grad():
        out = net(state, mask, ref, tags_a)
        torch.testing.assert_close(
            out.control, net(state, mask, ref, tags_b).control, rtol=0, atol=0
        )
        # the code is the softmax-weighted rows of the head's logits on the identifier
        summary = plant.identifier(state, mask)
        logits = summary @ plant.head.weight.T + plant.head.bias
        torch.testing.assert_close(out.plant.logits, logits)
        code, _ = plant(state, mask, ref, tags_a)
        torch.testing.assert_close(code, torch.softmax(logits, 1) @ plant.rows.weight)
        # a head sure of plant 3: the row of plant 3 exactly; of plant 7: another control
        plant.head.weight.zero_()
        plant.head.bias.fill_(-1e4)
        plant.head.bias[3] = 0.0
        torch.testing.assert_close(
            plant(state, mask, ref, tags_a)[0], plant.rows.weight[3].expand(6, -1)
        )
        u_3 = net(state, mask, ref, tags_a).control
        plant.head.bias[[3, 7]] = torch.tensor([-1e4, 0.0])
        assert not torch.allclose(u_3, net(state, mask, ref, tags_a).control)


def test_the_context_skip_scales_its_gains_by_exp_of_its_bounded_exponent():
    """u = u_rest + exp(s) u_skip: with s' = log 3 the skip path's part grows by e^s."""
    torch.manual_seed(0)
    net = Policy(_inferred()).net.eval()
    torch.nn.init.normal_(net.skip.gains.weight)
    batch = _batch(n=6)
    args = (batch["state"], batch["mask"], batch["ref"], torch.zeros(6, dtype=torch.long))
    with torch.no_grad():
        u1 = net(*args).control  # s = 0 at initialisation: a factor 1
        net.skip.scale.bias.fill_(math.log(3.0))
        u3 = net(*args).control
        net.skip.gains.weight.zero_()
        net.skip.gains.bias.zero_()
        rest = net(*args).control
    exponent = 6.0 * math.tanh(math.log(3.0) / 6.0)  # the bounded exponent, gain_range 6
    torch.testing.assert_close(u3 - rest, math.exp(exponent) * (u1 - rest), rtol=1e-4, atol=1e-5)
    assert (u1 - rest).abs().max() > 1e-2
    with pytest.raises(ValueError, match="model.skip.gain_range must be > 0"):
        from generalist_control.model.linear import ContextSkip

        ContextSkip(8, 3, 5, 8, 16, gain_range=0.0)


def test_the_context_skip_gains_follow_the_window():
    torch.manual_seed(0)
    net = Policy(_inferred()).net
    torch.nn.init.normal_(net.skip.gains.weight)
    gains = []
    net.skip.gains.register_forward_hook(lambda m, i, o: gains.append(o.detach()))
    for seed in (0, 1):
        b = _batch(n=6, seed=seed)
        net(b["state"], b["mask"], b["ref"], torch.zeros(6, dtype=torch.long))
    assert not torch.allclose(gains[0], gains[1])


def test_the_identity_loss_adds_the_weighted_cross_entropy_of_the_head():
    """Training loss = imitation MSE + w * CE(identity logits, tag), recomputed by hand."""
    torch.manual_seed(0)
    lit = ImitationModule(model=_inferred(loss_weight=0.5), optimizer=OPT).eval()
    batch = _batch()
    with torch.no_grad():
        loss = lit.training_step(batch, 0)
        p = lit.policy
        x, m, r, _, s = p.network_inputs(batch["state"], batch["mask"], batch["ref"], batch["tag"])
        out = p.net(*p.normaliser.normalise_inputs(batch["state"], batch["mask"], batch["ref"],
                                                   batch["tag"]))  # fmt: skip
        target = p.normaliser.normalise_controls(batch["target"], batch["tag"]) / out.scale
        mse = ((out.control - target) ** 2).mean()
        logits = out.plant.logits
        ce = -torch.log_softmax(logits, 1)[torch.arange(64), batch["tag"]].mean()
    torch.testing.assert_close(loss, mse + 0.5 * ce)


def test_the_identity_loss_trains_the_head_to_name_the_plant():
    """Windows whose history differs by plant: the head learns to tell them apart."""
    torch.manual_seed(0)
    lit = ImitationModule(model=_inferred(), optimizer=OPT)
    batch = _batch(n=200)
    batch["tag"] = torch.randint(0, 2, (200,), generator=torch.Generator().manual_seed(1))
    batch["state"][:, :, 0] += 3.0 * batch["tag"].unsqueeze(1)  # plant 1's first state offset
    opt = torch.optim.Adam(lit.parameters(), lr=1e-2)
    for _ in range(60):
        opt.zero_grad()
        lit.training_step(batch, 0).backward()
        opt.step()
    with torch.no_grad():
        _, out = lit.policy.errors(batch)
    assert float((out.plant.logits.argmax(1) == batch["tag"]).float().mean()) > 0.95


def test_a_policy_file_keeps_the_inferred_plant_and_drops_the_training_noise(tmp_path):
    """The noise is a setting of the part (training mode only); the loaded policy runs clean."""
    from generalist_control.model.policy import load_policy, save_policy
    from helpers import policy_meta

    torch.manual_seed(0)
    policy = Policy(_inferred(noise=0.5)).eval()
    path = save_policy(tmp_path / "p.ckpt", policy, policy_meta(["cstr"]))
    loaded, _ = load_policy(path)
    assert isinstance(loaded.net.plant, InferredPlant) and not loaded.training
    b = _batch(n=4)
    with torch.no_grad():
        a = policy(b["state"], b["mask"], b["ref"], b["tag"])[0]
        torch.testing.assert_close(loaded(b["state"], b["mask"], b["ref"], b["tag"])[0], a)
        loaded.train()
        assert not torch.equal(loaded(b["state"], b["mask"], b["ref"], b["tag"])[0], a)
