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

Normalisation is not here: :class:`~generalist_control.model.policy.Policy` wraps the network
with the fitted normaliser, and training, evaluation and deployment call that wrapper.
Where the paper is silent (``docs/training.md``): ``d_k = ceil(2 d_h / N_h)`` per head
(``W_O`` maps ``N_h d_k`` back to ``2 d_h``), and the one-hot tag is an embedding lookup.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from generalist_control.model.blocks import ExpertMLP, SummaryAttention, mlp
from generalist_control.model.identifier import TransitionSet, noisy_states
from generalist_control.model.net_config import (
    MODEL_DEFAULTS,
    input_width,
    law_history,
    network_config,
)

__all__ = [
    "MODEL_DEFAULTS",
    "ExpertMLP",
    "GeneralistNetwork",
    "SummaryAttention",
    "network_config",
    "count_parameters",
    "input_width",
]


#: The initial weight of each plant's evidence in its logit (``model.transition_models``).
EVIDENCE_WEIGHT = 4.0


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
        width, n_law = input_width(c), law_history(c)
        # Only the identifier (below) sees the previous control; the encoders and the linear
        # paths see the law's own state [x; z]. With the control in their input the
        # closed-loop score collapsed in training (measured, docs/training.md).
        law_width = width - c["control_history"]
        self.state_encoder_1 = mlp(law_width, d, e)
        self.state_encoder_2 = mlp(law_width, d, e)
        self.ref_encoder = mlp(1, d, e)
        # one-hot tag -> W_1 onehot + b_1 is a row lookup: an embedding of size d. Tag-free:
        # one shared row (the network never learns who is who); with unknown_tag one more
        # row, index n_tags, for a withheld tag (trained by tag dropout).
        # With infer_tag the plant's row is inferred: a softmax over the n_tags rows.
        rows = 1 if c["tag_free"] and not c["infer_tag"] else c["n_tags"] + c["unknown_tag"]
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
            n_in = (c["linear_samples"] or n_law) * (law_width + 1)
            self.linear = nn.Embedding(c["n_tags"] + c["unknown_tag"], c["horizon"] * n_in)
            nn.init.zeros_(self.linear.weight)
        # Ours (model.linear_skip): a linear path whose gains the network computes from the
        # learned tag embedding, W(e_tag) = A e_tag + b with A, b shared by every plant
        # (zero at initialisation). The LQI law is linear in the newest augmented state, so
        # this path can carry the feedback precisely, yet nothing in it is indexed by plant:
        # plants differ only through the embedding the rest of the network learns too.
        self.skip: nn.Linear | None = None
        if c["linear_skip"]:
            n_in = (c["linear_samples"] or n_law) * (law_width + 1)
            self.skip = nn.Linear(d, c["horizon"] * n_in)
            nn.init.zeros_(self.skip.weight)
            nn.init.zeros_(self.skip.bias)
        # Ours (model.skip_gain_scale): the gains times exp(s(code)), s zero at first, so the
        # context can scale them by orders of magnitude (LQI's gains span ~200x over plants).
        self.skip_scale: nn.Linear | None = None
        if c["skip_gain_scale"] and self.skip is not None:
            self.skip_scale = nn.Linear(d, 1)
            nn.init.zeros_(self.skip_scale.weight)
            nn.init.zeros_(self.skip_scale.bias)
        self._add_history_paths(d, width)
        # the slow LSTM sees samples ..., t - 2 tau, t - tau, t (always the newest one)
        self.slow_start = (n_law - 1) % c["stride"]

    def _add_history_paths(self, d: int, width: int) -> None:
        """The skip gains' context, the identifier feeding it and the head reading it."""
        c = self.config
        # Ours (model.history_context, with the skip path): the skip gains are computed from
        # the embedding plus a projection of the window's summary z, so that a policy without
        # its tag can still give each plant its own gains, inferred from the history.
        self.context: nn.Linear | None = None
        # with model.transition_models the identifier's state ends in each plant's evidence
        evidence = c["n_tags"] if c["transition_models"] else 0
        if c["history_context"] and self.skip is not None:
            self.context = nn.Linear((3 if c["control_history"] else 2) * d + evidence, d)
        # Ours (model.control_history): an LSTM over the whole window, previous controls
        # included, whose final state joins the context of the skip gains: it can identify
        # the plant from how its state answers the controls, and acts only through the gains.
        # With model.transition_identifier a set encoder of the window's one-step transitions
        # instead (generalist_control.model.identifier).
        self.identifier: nn.LSTM | TransitionSet | None = None
        if c["transition_identifier"]:
            self.identifier = TransitionSet.from_config(c, d)
        elif c["control_history"]:
            self.identifier = nn.LSTM(width + 1, d, batch_first=True)
        # Ours (model.identity_loss > 0): a linear read-out of the plant from the skip gains'
        # context, trained by cross-entropy against the tag (a training label only: the
        # network's output never depends on it), so the context must carry the identity.
        self.identity: nn.Linear | None = None
        if c["identity_head"]:
            self.identity = nn.Linear(d + evidence, c["n_tags"])
            if evidence:  # each plant's evidence starts as its logit (x EVIDENCE_WEIGHT)
                with torch.no_grad():
                    self.identity.weight[:, d:] = EVIDENCE_WEIGHT * torch.eye(evidence)
        #: Diagnostic only (``evaluation.identity_given``): with ``infer_tag``, the true
        #: plant's row instead of the head's inference. The tag is then given.
        self.identity_given = False
        #: Training mode only: the identifier's noise (``model.identity_noise``, set in training).
        self.identity_noise = 0.0
        #: Under that noise, fit the one-step models to the clean windows (set in training).
        self.identity_clean_fit = False
        #: The last :meth:`identify`'s evidence on clean windows (``identity_clean_fit``).
        self.fit_evidence: Tensor | None = None

    def features(self, state: Tensor, mask: Tensor, ref: Tensor, embedding: Tensor) -> Tensor:
        """Per-step features ``f_k`` (B, history, 2 * hidden) of the encoders.

        ``embedding`` (B, hidden): the plant's embedding row (:meth:`embedding`).
        """
        x = self.law_state(state, mask)
        f_tag = self.tag_encoder(embedding)  # the same at every step
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
        u, gates, _ = self.forward_code(state, mask, ref, tag)
        return u, gates

    def forward_code(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """:meth:`forward`, and what the identity head reads (B, hidden), or None.

        The skip gains' context (None without a skip path); with ``infer_tag`` the
        identifier's state. :meth:`identity_logits` reads the plant from it
        (``model.identity_loss``).
        """
        ident = self.identify(state, mask, ref)
        n_law = law_history(self.config)  # the law reads the newest n_law samples only
        state, mask, ref = state[:, -n_law:], mask[:, -n_law:], ref[:, -n_law:]
        code = None
        embedding = self.embedding(tag, ident)
        f = self.features(state, mask, ref, embedding)
        _, (h_fast, _) = self.lstm_fast(f)
        _, (h_slow, _) = self.lstm_slow(f[:, self.slow_start :: self.config["stride"]])
        z = torch.cat([h_fast[-1], h_slow[-1]], dim=-1)
        z_att = self.attention(z.unsqueeze(1)).squeeze(1)
        gates = torch.softmax(self.gate(z_att), dim=-1)
        u_experts = torch.stack([expert(z_att) for expert in self.experts], dim=1)
        u = torch.einsum("bm,bmk->bk", gates, u_experts)
        if self.linear is not None or self.skip is not None:
            if ident is not None:
                z_att = torch.cat([z_att, ident], dim=-1)
            u_linear, code = self._linear_paths(state, mask, ref, tag, embedding, z_att)
            u = u + u_linear
        if self.config["infer_tag"]:
            return u, gates, ident  # the identity head reads the identifier (embedding)
        return u, gates, code

    def identify(self, state: Tensor, mask: Tensor, ref: Tensor) -> Tensor | None:
        """The identifier's state (B, hidden; + n_tags evidence with transition_models)."""
        noise = self.identity_noise if self.training else 0.0  # the law's copy stays clean
        self.fit_evidence = None
        if isinstance(self.identifier, TransitionSet):
            # detached: the models' fit moves their own layer, never the rows the law reads
            rows = self.tag_embedding.weight[: self.config["n_tags"]].detach()
            models = self.identifier.models is not None
            ident, self.fit_evidence = self.identifier.read(
                state, mask, rows if models else None, noise, self.identity_clean_fit
            )
            return ident
        if noise > 0:
            state = noisy_states(state, mask, noise, self.config["state_dim"])
        if self.identifier is not None:
            seq = torch.cat([state * mask, ref.unsqueeze(-1)], dim=-1)
            return self.identifier(seq)[1][0][-1]
        return None

    def embedding(self, tag: Tensor, ident: Tensor | None = None) -> Tensor:
        """The plant's embedding row (B, hidden) that the encoders and the skip gains see.

        The tag's row; one shared row when ``tag_free``; with ``infer_tag`` the rows weighed
        by the identity head's softmax over the plants, read from the identifier's state
        ``ident`` (the tag is not used), unless :attr:`identity_given` is set.
        """
        if not self.config["infer_tag"]:
            return self.tag_embedding(self.tag_index(tag))
        if self.identity_given:
            return self.tag_embedding(tag)
        if ident is None or self.identity is None:
            raise ValueError("infer_tag needs the identifier and the identity head")
        weights = torch.softmax(self.identity(ident), dim=-1)
        return weights @ self.tag_embedding.weight[: self.config["n_tags"]]

    def identity_logits(self, code: Tensor) -> Tensor:
        """Logits (B, n_tags) of the plant read from ``code`` (see :meth:`forward_code`).

        Raises
        ------
        ValueError
            If the network has no identity head (``model.identity_loss`` is 0).
        """
        if self.identity is None:
            raise ValueError("the network has no identity head: set model.identity_loss > 0")
        return self.identity(code)

    def transition_fit(self, code: Tensor, tag: Tensor) -> Tensor:
        """How badly the true plants' one-step models fit their windows (>= 0; 0 without).

        ``code``: the identifier's state (:meth:`forward_code` with ``infer_tag``).
        """
        models = getattr(self.identifier, "models", None)
        if models is None:
            return code.new_zeros(())
        clean = self.fit_evidence  # the clean windows' evidence under identity noise
        return models.fit_loss(code[:, -self.config["n_tags"] :] if clean is None else clean, tag)

    def tag_index(self, tag: Tensor) -> Tensor:
        """The embedding row of each tag: row 0 for every plant when ``tag_free``.

        The withheld tag is ``n_tags`` (a row only with ``unknown_tag``);
        :meth:`~generalist_control.model.policy.Policy.network_tags` refuses to withhold it
        from a network without that row.
        """
        return torch.zeros_like(tag) if self.config["tag_free"] else tag

    def _linear_paths(
        self,
        state: Tensor,
        mask: Tensor,
        ref: Tensor,
        tag: Tensor,
        embedding: Tensor,
        summary: Tensor,
    ) -> tuple[Tensor, Tensor | None]:
        """The per-tag head and the embedding-conditioned skip path, and the skip's context."""
        window = self.linear_features(state, mask, ref)
        shape = (-1, self.config["horizon"], window.shape[1])
        u = window.new_zeros(window.shape[0], self.config["horizon"])
        code = None
        if self.linear is not None:
            u = u + torch.einsum("bkf,bf->bk", self.linear(tag).view(shape), window)
        if self.skip is not None:
            code = embedding
            if self.context is not None:
                code = code + self.context(summary)
            gains = self.skip(code).view(shape)
            if self.skip_scale is not None:  # exponent bounded: a factor within e^+-6
                exponent = 6.0 * torch.tanh(self.skip_scale(code) / 6.0)
                gains = gains * torch.exp(exponent).unsqueeze(-1)
            u = u + torch.einsum("bkf,bf->bk", gains, window)
        return u, code

    def linear_features(self, state: Tensor, mask: Tensor, ref: Tensor) -> Tensor:
        """What the linear paths see: the newest ``linear_samples`` of state and reference.

        Without the previous-control channel (``control_history``), which only the
        identifier sees.
        """
        n = self.config["linear_samples"] or law_history(self.config)
        return torch.cat([self.law_state(state, mask)[:, -n:].flatten(1), ref[:, -n:]], dim=1)

    def law_state(self, state: Tensor, mask: Tensor) -> Tensor:
        """The paper's ``X ⊙ M`` without the previous-control channel: ``[x; z]`` per step."""
        return (state * mask)[..., : state.shape[-1] - self.config["control_history"]]


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters of ``module``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
