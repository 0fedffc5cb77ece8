"""The transition-set identifier of an inferred plant, and a law that reads part of the window."""

from __future__ import annotations

import pytest
import torch

from generalist_control.model.identifier import TransitionSet
from helpers import build_net

CHANNELS = ["integral", "previous_control"]


def _window(batch: int, history: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Windows of 4 padded states, the integral and the previous control; order 3."""
    g = torch.Generator().manual_seed(seed)
    state = torch.randn(batch, history, 6, generator=g)
    mask = torch.ones(batch, history, 6)
    mask[..., 3] = 0.0
    return state * mask, mask, torch.randn(batch, history, generator=g)


def test_transitions_pair_each_state_change_with_the_control_that_caused_it():
    """Built by hand: (x_j, x_(j+1) - x_j, u_j, order mask), u_j read at sample j + 1."""
    state, mask, _ = _window(2, 5)
    enc = TransitionSet(state_dim=4, hidden=8)
    got = enc.transitions(state, mask)
    assert got.shape == (2, 4, 13)
    for b in range(2):
        for j in range(4):
            x, x_next = state[b, j, :4], state[b, j + 1, :4]
            u = state[b, j + 1, 5]  # the control applied at j, as the window holds it at j + 1
            want = torch.cat([x, x_next - x, u.view(1), torch.tensor([1.0, 1.0, 1.0, 0.0])])
            torch.testing.assert_close(got[b, j], want)
    assert float(got[..., 3].abs().max()) == 0.0  # padding stays zero
    assert float(got[..., 7].abs().max()) == 0.0


def test_transition_identifier_is_a_mean_over_transitions_in_any_order():
    """tanh(rho(mean phi)): the transitions' order does not matter, their values do."""
    torch.manual_seed(0)
    enc = TransitionSet(state_dim=4, hidden=8)
    state, mask, _ = _window(3, 7)
    t = enc.transitions(state, mask)
    by_hand = torch.tanh(enc.rho(torch.stack([enc.phi(t[:, j]) for j in range(6)]).mean(0)))
    torch.testing.assert_close(enc(state, mask), by_hand)
    shuffled = t[:, torch.randperm(6)]
    torch.testing.assert_close(torch.tanh(enc.rho(enc.phi(shuffled).mean(1))), by_hand)
    state2 = state.clone()
    state2[:, 0, 0] += 1.0  # the oldest sample: one transition changes, the state does
    assert not torch.allclose(enc(state2, mask), by_hand)
    with pytest.raises(ValueError, match="at least 2 samples"):
        enc(state[:, :1], mask[:, :1])


def test_law_history_reads_the_newest_samples_of_the_window():
    """A law on the newest 8 of 24 samples is the 8-sample network with the same weights."""
    torch.manual_seed(0)
    short = build_net(channels=CHANNELS, skip="linear").eval()
    long = build_net(channels=CHANNELS, skip="linear", history=24, law_history=8).eval()
    torch.nn.init.normal_(short.skip.gains.weight)
    long.load_state_dict(short.state_dict())
    state, mask, ref = _window(4, 24)
    tag = torch.tensor([0, 3, 7, 24])
    with torch.no_grad():
        torch.testing.assert_close(
            long(state, mask, ref, tag).control,
            short(state[:, -8:], mask[:, -8:], ref[:, -8:], tag).control,
        )


def test_an_inferred_plant_reads_samples_the_law_does_not():
    torch.manual_seed(0)
    net = build_net(channels=CHANNELS, skip="context", history=24, law_history=8,
                    plant="inferred", models=None).eval()  # fmt: skip
    assert isinstance(net.plant.identifier, TransitionSet)
    torch.nn.init.normal_(net.skip.gains.weight)
    state, mask, ref = _window(4, 24)
    tag = torch.zeros(4, dtype=torch.long)
    old = state.clone()
    old[:, :16, :3] += torch.randn(4, 16, 3)  # only samples older than the law's 8
    with torch.no_grad():
        u, u_old = net(state, mask, ref, tag).control, net(old, mask, ref, tag).control
        assert not torch.allclose(u, u_old)  # through the identifier alone
        # cut both paths: the head weighs every row alike, the skip ignores the summary
        net.plant.head.weight.zero_()
        net.skip.context.weight.zero_()
        torch.testing.assert_close(
            net(state, mask, ref, tag).control, net(old, mask, ref, tag).control
        )


def test_an_inferred_plant_without_the_previous_control_is_refused():
    with pytest.raises(ValueError, match=r"reads the window's \['previous_control'\] channel"):
        build_net(channels=["integral"], plant="inferred")
