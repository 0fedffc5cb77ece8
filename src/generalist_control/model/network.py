"""The Generalist Controller network (paper, Section 4).

One forward pass maps a window of normalised inputs to ``horizon`` normalised controls:

1. *Feature encoding*, per time step of the ``history``-step window: two state encoders on
   the masked, zero-padded state ``X * M``, a reference encoder and a system-tag encoder,
   each a two-layer ReLU MLP with output size ``hidden // 2``; their outputs are
   concatenated into ``d_f = 2 * hidden`` features per step.
2. *Temporal processing*: an LSTM over all ``history`` feature vectors and a second LSTM
   over the sequence subsampled with stride ``stride`` (ending at the newest sample), both
   of size ``d_h = hidden``; their final hidden states are concatenated into
   ``z`` (``2 * hidden``), then multi-head attention with a residual, ``z + W_O a(z)``.
3. *Mixture of experts*: ``experts`` three-layer MLPs (ReLU, LayerNorm after each hidden
   layer) each give ``horizon`` controls; a softmax gate on ``z_att`` weighs them.

Normalisation is not part of this module: :class:`generalist_control.model.policy.Policy`
wraps it with the :class:`~generalist_control.model.normalise.Normaliser` fitted on the training
split, and that wrapper is what training, evaluation and deployment call.

Choices where the paper is silent or inconsistent are documented in ``docs/training.md``:
the per-head size is ``d_k = ceil(2 d_h / N_h)`` (so ``N_h = 3`` works at any ``d_h``, with
``W_O`` mapping ``N_h d_k`` back to ``2 d_h``), and the tag enters as a one-hot vector,
implemented as an embedding lookup (the same function as ``W_1 onehot + b_1``).
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from generalist_control.common.schema import require_int, require_switch
from generalist_control.plants.plant import MAX_ORDER

__all__ = [
    "MODEL_DEFAULTS",
    "ExpertMLP",
    "GeneralistNetwork",
    "SummaryAttention",
    "network_config",
    "count_parameters",
    "input_width",
]


#: Network config keys and defaults: ``hidden`` (d), ``heads`` (N_h), ``stride`` (tau),
#: ``history`` (T_h), ``horizon`` (K), ``experts`` (M), ``n_tags``, ``state_dim`` (n_max),
#: ``window_scale`` (0 or 1: per-window amplitude scaling in
#: :class:`~generalist_control.model.policy.Policy`; 0 is the paper's recipe), ``linear_head``
#: (0 or 1: add a per-tag linear map of the window to the output; 0 is the paper's),
#: ``integral`` (0 or 1: the window's state carries one more channel, the integral of the
#: tracking error that the LQI expert itself integrates; 0 is the paper's),
#: ``linear_samples`` (how many of the newest samples the linear head sees; 0, the default, is
#: the whole window; 1 with ``integral``, where the LQI law is linear in the newest
#: augmented state alone), ``linear_skip`` (0 or 1: a linear map of those samples added to
#: the output, its gains computed from the learned tag embedding by one shared linear
#: layer: the plant enters only through the embedding; 0 is the paper's), ``tag_free`` (0 or
#: 1: the network never receives the plant's identity, one shared embedding row replaces
#: the tag), ``unknown_tag`` (0 or 1: the embedding has one more row, index ``n_tags``, the
#: "tag withheld" that tag dropout trains; see :class:`~generalist_control.model.policy.Policy`)
#: and ``history_context`` (0 or 1: the skip path's gains are computed from the embedding
#: plus a learned projection of the window's summary, so the plant can be inferred from its
#: history; 0 is the default recipe) and ``control_history`` (0 or 1: the window carries one
#: more channel, the control applied one sample earlier, which only an identifier LSTM sees,
#: whose state joins the skip gains' context, so a state change can be read against the
#: control that caused it; needs ``linear_skip`` and ``history_context``; 0 is the default).
MODEL_DEFAULTS: dict[str, int] = {
    "hidden": 32,
    "heads": 3,
    "stride": 2,
    "history": 8,
    "horizon": 3,
    "experts": 3,
    "n_tags": 25,
    "state_dim": MAX_ORDER,
    "window_scale": 0,
    "linear_head": 0,
    "integral": 0,
    "linear_samples": 0,
    "linear_skip": 0,
    "tag_free": 0,
    "unknown_tag": 0,
    "history_context": 0,
    "control_history": 0,
}

#: Keys that are switches (0 or 1) rather than sizes.
_SWITCHES = (
    "window_scale",
    "linear_head",
    "integral",
    "linear_skip",
    "tag_free",
    "unknown_tag",
    "history_context",
    "control_history",
)

#: Where a network key is set in the training config, when not at ``model.<key>``.
_CONFIG_KEYS = {"experts": "experts", "history": "data.history", "horizon": "data.horizon"}


def input_width(config: dict[str, int]) -> int:
    """Width of the state input per step: ``state_dim`` (+1 each: integral, previous control)."""
    extra = int(config.get("integral", 0)) + int(config.get("control_history", 0))
    return int(config["state_dim"]) + extra


def network_config(**kwargs: Any) -> dict[str, int]:
    """Complete and check a network config; a plain ``dict`` (checkpoints store it as is).

    Values are taken as they are, never rounded: a size must be an integer (a float, even
    ``32.0``, a boolean or a string is refused), a switch a boolean or 0 or 1.

    Raises
    ------
    ValueError
        If a key is unknown, a size is not a positive integer (``linear_samples``: not
        negative), a switch is not 0 or 1, or ``hidden`` is odd; the message names the
        config key (``model.hidden``, ``experts``, ``data.history``), the value and its type.
    """
    unknown = set(kwargs) - set(MODEL_DEFAULTS)
    if unknown:
        raise ValueError(
            f"unknown model config keys {sorted(unknown)}; known: {sorted(MODEL_DEFAULTS)}"
        )
    cfg: dict[str, int] = {}
    for key, default in MODEL_DEFAULTS.items():
        value, name = kwargs.get(key, default), _CONFIG_KEYS.get(key, f"model.{key}")
        if key in _SWITCHES:
            cfg[key] = require_switch(name, value)
        else:
            cfg[key] = require_int(name, value, minimum=0 if key == "linear_samples" else 1)
    if cfg["linear_samples"] > cfg["history"]:
        raise ValueError(
            f"model.linear_samples ({cfg['linear_samples']}) exceeds the history "
            f"({cfg['history']})"
        )
    if cfg["tag_free"] and cfg["linear_head"]:
        raise ValueError(
            "model.linear_head is a table of gains per tag and model.tag_free withholds the "
            "tag: turn one of them off"
        )
    if cfg["control_history"] and not (cfg["linear_skip"] and cfg["history_context"]):
        raise ValueError(
            "model.control_history feeds the skip path's gains (model.linear_skip and "
            "model.history_context): turn those on, or control_history off"
        )
    if cfg["hidden"] % 2:
        raise ValueError(f"model.hidden must be even (encoders give hidden // 2), got {cfg}")
    return cfg


def _mlp(n_in: int, n_hidden: int, n_out: int) -> nn.Sequential:
    """Two-layer encoder ``W_2 relu(W_1 x + b_1) + b_2`` (paper, Eq. f_1..f_4)."""
    return nn.Sequential(nn.Linear(n_in, n_hidden), nn.ReLU(), nn.Linear(n_hidden, n_out))


class SummaryAttention(nn.Module):
    """Multi-head scaled dot-product attention with a residual: ``z + W_O [a_1 .. a_H]``.

    Parameters
    ----------
    dim : int
        Token size (``2 d_h`` in the paper).
    heads : int
        ``N_h``. Each head has ``d_k = ceil(dim / heads)``; the concatenated heads
        (``heads * d_k``, which may exceed ``dim``) are projected back to ``dim`` by ``W_O``.

    Notes
    -----
    As in the paper the tokens are the temporal summary ``z`` alone (one token per window),
    so the softmax over a single key is identically one and the block computes
    ``z + W_O V z``; the query and key projections are kept for fidelity with the paper
    (and its parameter count), but receive zero gradient (up to rounding).
    """

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.d_k = math.ceil(dim / heads)
        inner = heads * self.d_k
        self.qkv = nn.Linear(dim, 3 * inner)
        self.out = nn.Linear(inner, dim)

    def forward(self, tokens: Tensor) -> Tensor:
        """Attend over ``tokens`` (B, T, dim); return the same shape."""
        B, T, _ = tokens.shape
        qkv = self.qkv(tokens).view(B, T, 3, self.heads, self.d_k).permute(2, 0, 3, 1, 4)
        a = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])  # (B, heads, T, d_k)
        return tokens + self.out(a.transpose(1, 2).reshape(B, T, self.heads * self.d_k))


class ExpertMLP(nn.Sequential):
    """One expert: three linear layers, ReLU then LayerNorm after each hidden layer."""

    def __init__(self, n_in: int, n_hidden: int, n_out: int) -> None:
        super().__init__(
            nn.Linear(n_in, n_hidden),
            nn.ReLU(),
            nn.LayerNorm(n_hidden),
            nn.Linear(n_hidden, n_hidden),
            nn.ReLU(),
            nn.LayerNorm(n_hidden),
            nn.Linear(n_hidden, n_out),
        )


class GeneralistNetwork(nn.Module):
    """The network of the paper on *normalised* inputs (see the module docstring).

    Parameters
    ----------
    hidden, heads, stride, history, horizon, experts, n_tags, state_dim : int
        See :data:`MODEL_DEFAULTS`.

    Examples
    --------
    >>> net = GeneralistNetwork(hidden=32, experts=3)
    >>> B = 5
    >>> u, gates = net(torch.zeros(B, 8, 4), torch.ones(B, 8, 4), torch.zeros(B, 8),
    ...                torch.zeros(B, dtype=torch.long))
    >>> tuple(u.shape), tuple(gates.shape)
    ((5, 3), (5, 3))
    """

    def __init__(self, **config: Any) -> None:
        super().__init__()
        self.config = network_config(**config)
        c = self.config
        d, e = c["hidden"], c["hidden"] // 2
        width = input_width(c)
        # Only the identifier (below) sees the previous control; the encoders and the linear
        # paths see the law's own state [x; z]. With the control in their input the
        # closed-loop score collapsed in training (measured, docs/training.md).
        law_width = width - c["control_history"]
        self.state_encoder_1 = _mlp(law_width, d, e)
        self.state_encoder_2 = _mlp(law_width, d, e)
        self.ref_encoder = _mlp(1, d, e)
        # one-hot tag -> W_1 onehot + b_1 is a row lookup: an embedding of size d. Tag-free:
        # one shared row (the network never learns who is who); with unknown_tag one more
        # row, index n_tags, for a withheld tag (trained by tag dropout).
        rows = 1 if c["tag_free"] else c["n_tags"] + c["unknown_tag"]
        self.tag_embedding = nn.Embedding(rows, d)
        self.tag_encoder = nn.Sequential(nn.ReLU(), nn.Linear(d, e))
        self.lstm_fast = nn.LSTM(4 * e, d, batch_first=True)
        self.lstm_slow = nn.LSTM(4 * e, d, batch_first=True)
        self.attention = SummaryAttention(2 * d, c["heads"])
        self.experts = nn.ModuleList(
            ExpertMLP(2 * d, d, c["horizon"]) for _ in range(c["experts"])
        )
        self.gate = nn.Linear(2 * d, c["experts"])
        # Ours (model.linear_head): a per-tag linear map of the whole window, added to the
        # experts' output. For a linear plant the LQI law is exactly linear in two
        # consecutive states and the reference (its integrator is recoverable from
        # x_k - Ad x_(k-1)), so the head can carry the feedback precisely and the
        # experts the rest. Zero at initialisation: training starts from the paper's net.
        # With model.integral the law is linear in the newest augmented state [x; z] alone
        # (linear_samples = 1): the head is then the LQI law's own form.
        self.linear: nn.Embedding | None = None
        if c["linear_head"]:
            n_in = (c["linear_samples"] or c["history"]) * (law_width + 1)
            self.linear = nn.Embedding(c["n_tags"] + c["unknown_tag"], c["horizon"] * n_in)
            nn.init.zeros_(self.linear.weight)
        # Ours (model.linear_skip): a linear path whose gains the network computes from the
        # learned tag embedding, W(e_tag) = A e_tag + b with A, b shared by every plant
        # (zero at initialisation). The LQI law is linear in the newest augmented state, so
        # this path can carry the feedback precisely, yet nothing in it is indexed by plant:
        # plants differ only through the embedding the rest of the network learns too.
        self.skip: nn.Linear | None = None
        if c["linear_skip"]:
            n_in = (c["linear_samples"] or c["history"]) * (law_width + 1)
            self.skip = nn.Linear(d, c["horizon"] * n_in)
            nn.init.zeros_(self.skip.weight)
            nn.init.zeros_(self.skip.bias)
        self._add_history_paths(d, width)
        # the slow LSTM sees samples ..., t - 2 tau, t - tau, t (always the newest one)
        self.slow_start = (c["history"] - 1) % c["stride"]

    def _add_history_paths(self, d: int, width: int) -> None:
        """The skip gains' context from the history, and the identifier that feeds it."""
        c = self.config
        # Ours (model.history_context, with the skip path): the skip gains are computed from
        # the embedding plus a projection of the window's summary z, so that a policy without
        # its tag can still give each plant its own gains, inferred from the history.
        self.context: nn.Linear | None = None
        if c["history_context"] and self.skip is not None:
            self.context = nn.Linear((3 if c["control_history"] else 2) * d, d)
        # Ours (model.control_history): an LSTM over the whole window, previous controls
        # included, whose final state joins the context of the skip gains: it can identify
        # the plant from how its state answers the controls, and acts only through the gains.
        self.identifier: nn.LSTM | None = None
        if c["control_history"]:
            self.identifier = nn.LSTM(width + 1, d, batch_first=True)

    def features(self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor) -> Tensor:
        """Per-step features ``f_k`` (B, history, 2 * hidden) of the encoders."""
        x = self.law_state(state, mask)
        f_tag = self.tag_encoder(self.tag_embedding(self.tag_index(tag)))  # same at every step
        return torch.cat(
            [
                self.state_encoder_1(x),
                self.state_encoder_2(x),
                self.ref_encoder(ref.unsqueeze(-1)),
                f_tag.unsqueeze(1).expand(-1, x.shape[1], -1),
            ],
            dim=-1,
        )

    def forward(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Controls and gate weights for a batch of normalised windows.

        Parameters
        ----------
        state, mask : Tensor, shape (B, history, width)
            ``width`` = :func:`input_width`: ``state_dim``, plus the error integral and
            the previous control where switched on.
        ref : Tensor, shape (B, history)
        tag : Tensor of int, shape (B,)

        Returns
        -------
        u : Tensor, shape (B, horizon)
            Normalised control sequence ``sum_i alpha_i u^(i)``.
        gates : Tensor, shape (B, experts)
            Softmax gate weights ``alpha`` (rows sum to one).
        """
        f = self.features(state, mask, ref, tag)
        _, (h_fast, _) = self.lstm_fast(f)
        _, (h_slow, _) = self.lstm_slow(f[:, self.slow_start :: self.config["stride"]])
        z = torch.cat([h_fast[-1], h_slow[-1]], dim=-1)
        z_att = self.attention(z.unsqueeze(1)).squeeze(1)
        gates = torch.softmax(self.gate(z_att), dim=-1)
        u_experts = torch.stack([expert(z_att) for expert in self.experts], dim=1)
        u = torch.einsum("bm,bmk->bk", gates, u_experts)
        if self.linear is not None or self.skip is not None:
            if self.identifier is not None:
                seq = torch.cat([state * mask, ref.unsqueeze(-1)], dim=-1)
                z_att = torch.cat([z_att, self.identifier(seq)[1][0][-1]], dim=-1)
            u = u + self._linear_paths(state, mask, ref, tag, z_att)
        return u, gates

    def tag_index(self, tag: Tensor) -> Tensor:
        """The embedding row of each tag: row 0 for every plant when ``tag_free``.

        The withheld tag is ``n_tags`` (a row only with ``unknown_tag``);
        :meth:`~generalist_control.model.policy.Policy.network_tags` refuses to withhold it
        from a network without that row.
        """
        return torch.zeros_like(tag) if self.config["tag_free"] else tag

    def _linear_paths(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor, summary: Tensor
    ) -> Tensor:
        """The per-tag head and the embedding-conditioned skip path, on the newest samples."""
        window = self.linear_features(state, mask, ref)
        shape = (-1, self.config["horizon"], window.shape[1])
        u = window.new_zeros(window.shape[0], self.config["horizon"])
        if self.linear is not None:
            u = u + torch.einsum("bkf,bf->bk", self.linear(tag).view(shape), window)
        if self.skip is not None:
            code = self.tag_embedding(self.tag_index(tag))
            if self.context is not None:
                code = code + self.context(summary)
            gains = self.skip(code).view(shape)
            u = u + torch.einsum("bkf,bf->bk", gains, window)
        return u

    def linear_features(self, state: Tensor, mask: Tensor, ref: Tensor) -> Tensor:
        """What the linear paths see: the newest ``linear_samples`` of state and reference.

        Without the previous-control channel (``control_history``), which only the
        identifier sees.
        """
        n = self.config["linear_samples"] or self.config["history"]
        return torch.cat([self.law_state(state, mask)[:, -n:].flatten(1), ref[:, -n:]], dim=1)

    def law_state(self, state: Tensor, mask: Tensor) -> Tensor:
        """The paper's ``X ⊙ M`` without the previous-control channel: ``[x; z]`` per step."""
        return (state * mask)[..., : state.shape[-1] - self.config["control_history"]]


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters of ``module``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
