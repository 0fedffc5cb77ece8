"""The deployable policy: normaliser + network, and its checkpoint file.

:class:`Policy` is the single preprocessing path of the project: training computes its
loss on :meth:`Policy.normalised`, and evaluation and deployment call :meth:`Policy.forward`
(raw plant units in and out) or :meth:`Policy.predict_windows` on
:class:`~generalist_control.data.windows.Windows` built by the one window builder.

A policy file (``models/policy.ckpt``) holds plain types and tensors only, so it loads with
``torch.load(path, weights_only=True)``::

    {"format_version": 1, "model": {...network config...}, "state_dict": {...},
     "meta": {"tags": {plant: tag}, "orders": {plant: n}, "dt": ..., "history": ...,
              "horizon": ..., "content_hash": "sha256:...", "metrics": {...}, ...}}

:func:`load_policy` reads such a file or a Lightning checkpoint written by training.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from generalist_control.data.windows import Windows
from generalist_control.model.network import GeneralistNetwork, input_width, network_config
from generalist_control.model.normalise import Normaliser

__all__ = [
    "POLICY_FILE",
    "POLICY_FORMAT_VERSION",
    "Policy",
    "load_policy",
    "save_policy",
]

POLICY_FORMAT_VERSION = 1

#: File name of a policy: ``models/policy.ckpt`` and the MLflow artifact ``policy/policy.ckpt``.
POLICY_FILE = "policy.ckpt"

#: Smallest window scale (normalised units): a window at rest maps to inputs near zero.
WINDOW_SCALE_FLOOR = 1e-3


class Policy(nn.Module):
    """Normaliser and network: raw windows in, controls in plant units out.

    Parameters
    ----------
    model : dict
        Network config (see :data:`generalist_control.model.network.MODEL_DEFAULTS`).
    """

    def __init__(self, model: dict[str, Any]) -> None:
        super().__init__()
        self.config = network_config(**model)
        self.normaliser = Normaliser(self.config["n_tags"], input_width(self.config))
        self.net = GeneralistNetwork(**self.config)
        #: Run with the tag withheld (evaluation.withhold_tag): the network gets the
        #: "unknown" row instead of the plant's tag; the per-plant data scales still apply.
        self.withhold_tag = False

    def network_tags(self, tag: Tensor, withheld: Tensor | None = None) -> Tensor:
        """The tags the network receives: ``n_tags`` (withheld) where ``withheld`` is true.

        Parameters
        ----------
        tag : Tensor of int, shape (B,)
        withheld : Tensor of bool, shape (B,), optional
            Which samples go without their tag (tag dropout in training); None: all of them
            when :attr:`withhold_tag` is set, none otherwise.

        Raises
        ------
        ValueError
            If a tag is withheld from a network trained with its tag always given.
        """
        if withheld is None:
            if not self.withhold_tag:
                return tag
            withheld = torch.ones_like(tag, dtype=torch.bool)
        if self.config["tag_free"]:
            return tag  # the network ignores it anyway
        if not self.config["unknown_tag"]:
            raise ValueError(
                "cannot withhold the tag: this policy was trained with its tag always given; "
                "train with model.tag_dropout > 0 (or model.tag_free=true)"
            )
        return torch.where(withheld, torch.full_like(tag, self.config["n_tags"]), tag)

    def scaled(
        self,
        state: Tensor,
        mask: Tensor,
        ref: Tensor,
        tag: Tensor,
        withheld: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
        """Output (window-scaled units), gates, window scales (B, 1), identity-head input.

        The last is what the identity head reads (None without a skip path; see
        ``model.identity_loss``). With ``window_scale`` on, each window's normalised
        state and reference are divided by their largest magnitude ``s`` (at least
        :data:`WINDOW_SCALE_FLOOR`) and the network's output is multiplied by it. The
        LQI law is linear, so its step responses from rest are exactly proportional to
        the step: scaled windows of every amplitude coincide, the network learns one
        shape per plant, and its error is relative to the signal, as precise for a unit
        step as for a step of 20. With it off, ``s = 1``. The data scales use the
        plant's tag; the network gets :meth:`network_tags`.
        """
        state, mask, ref, tag, s = self.network_inputs(state, mask, ref, tag)
        u, gates, code = self.net.forward_code(state, mask, ref, self.network_tags(tag, withheld))
        return u, gates, s, code

    def identity_logits(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, Tensor]:
        """The network's output (window-scaled units) and its plant logits (B, n_tags).

        The logits are the identity head's read-out of the skip gains' context, or with
        ``infer_tag`` of the identifier's state (``model.identity_loss``); the tag only
        scales the data, as in :meth:`scaled`.

        Raises
        ------
        ValueError
            If the network has no skip path or no identity head.
        """
        u, _, _, code = self.scaled(state, mask, ref, tag)
        if code is None:
            raise ValueError("the network has no skip path, so no identity context")
        return u, self.net.identity_logits(code)

    def network_inputs(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Raw windows -> the network's inputs (normalised, window-scaled) and the scales s."""
        state, mask, ref, tag = self.normaliser.normalise_inputs(state, mask, ref, tag)
        if self.config["window_scale"]:
            peak = torch.maximum(state.abs().amax(dim=(1, 2)), ref.abs().amax(dim=1))
            s = peak.clamp(min=WINDOW_SCALE_FLOOR).unsqueeze(1)
            return state / s.unsqueeze(2), mask, ref / s, tag, s
        return state, mask, ref, tag, torch.ones_like(ref[:, :1])

    @torch.no_grad()
    def fit_linear_head(
        self,
        state: Tensor,
        mask: Tensor,
        ref: Tensor,
        tag: Tensor,
        target: Tensor,
        ridge: float = 1e-8,
    ) -> dict[int, float]:
        """Set the linear head to the per-tag least-squares fit of ``target``; zero the experts.

        A closed-form start for training (``model.linear_init: lstsq``): for each tag, the
        head's weights solve the ridge-regularised least-squares problem from its features
        (:meth:`GeneralistNetwork.linear_features` of the network's inputs) to the
        targets in the units the loss uses, and each expert's last layer is zeroed so that
        the policy starts as exactly that linear law; the experts then learn the remainder
        (for a nonlinear plant) by gradient descent. For a linear plant with
        ``model.integral`` and ``linear_samples = 1`` the fit recovers the LQI law
        ``-Kx x - Ki z`` from the data alone.

        Returns
        -------
        dict
            Per tag, the fit's relative RMS residual.
        """
        if self.net.linear is None:
            raise ValueError("the policy has no linear head (model.linear_head=false)")
        x, m, r, t, s = self.network_inputs(state, mask, ref, tag)
        feats = self.net.linear_features(x, m, r).double()
        y = (self.normaliser.normalise_controls(target, tag) / s).double()
        weight = self.net.linear.weight
        residuals = {}
        for tg in torch.unique(t).tolist():
            sel = t == tg
            X, Y = feats[sel], y[sel]
            G = X.T @ X
            G += (
                ridge
                * (torch.trace(G) / G.shape[0] + 1e-30)
                * torch.eye(G.shape[0], dtype=G.dtype)
            )
            W = torch.linalg.solve(G, X.T @ Y)  # (F, K)
            weight[tg] = W.T.reshape(-1).to(weight.dtype)
            res = Y - X @ W
            residuals[int(tg)] = float(
                res.pow(2).mean().sqrt() / Y.pow(2).mean().sqrt().clamp(min=1e-30)
            )
        for expert in self.net.experts:
            last = expert[-1]  # type: ignore[index]  # an ExpertMLP (nn.Sequential)
            last.weight.zero_()
            last.bias.zero_()
        return residuals

    def normalised(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Network output in normalised units and gate weights."""
        u, gates, s, _ = self.scaled(state, mask, ref, tag)
        return u * s, gates

    def forward(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Controls ``u[k .. k + horizon - 1]`` in plant units (B, horizon) and gates (B, M).

        Inputs are raw windows as built by :func:`generalist_control.data.windows.build_windows`.
        """
        u, gates = self.normalised(state, mask, ref, tag)
        return self.normaliser.denormalise_controls(u, tag), gates

    @torch.no_grad()
    def predict_windows(
        self, windows: Windows, batch_size: int = 8192
    ) -> tuple[np.ndarray, np.ndarray]:
        """Controls (W, horizon) and gate weights (W, M) for ``windows``, as float32 arrays."""
        self.eval()
        device = next(self.parameters()).device
        us, gs = [], []
        for i in range(0, len(windows), batch_size):
            sl = slice(i, i + batch_size)
            args = [
                torch.as_tensor(np.asarray(a[sl]), device=device)
                for a in (windows.state, windows.mask, windows.ref, windows.tag)
            ]
            u, g = self(*args)
            us.append(u.cpu().numpy())
            gs.append(g.cpu().numpy())
        horizon, experts = self.config["horizon"], self.config["experts"]
        if not us:
            return np.zeros((0, horizon), np.float32), np.zeros((0, experts), np.float32)
        return np.concatenate(us), np.concatenate(gs)


def save_policy(path: str | Path, policy: Policy, meta: dict[str, Any]) -> Path:
    """Write ``policy`` and plain-typed ``meta`` to ``path`` (see the module docstring)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu() for k, v in policy.state_dict().items()}
    blob = {
        "format_version": POLICY_FORMAT_VERSION,
        "model": dict(policy.config),
        "state_dict": state,
        "meta": meta,
    }
    tmp = path.with_name(path.name + ".tmp")
    torch.save(blob, tmp)
    tmp.replace(path)
    return path


def load_policy(
    path: str | Path, map_location: str | torch.device = "cpu"
) -> tuple[Policy, dict[str, Any]]:
    """Load a policy file or a training (Lightning) checkpoint; return it with its meta.

    The policy is in eval mode. Loading uses ``weights_only=True``: no code is unpickled.
    """
    blob = torch.load(path, map_location=map_location, weights_only=True)
    if "pytorch-lightning_version" in blob:  # a checkpoint of LitController
        hp = blob["hyper_parameters"]
        model, meta = hp["model"], dict(hp.get("meta", {}))
        state = {k[len("policy.") :]: v for k, v in blob["state_dict"].items()}
    else:
        version = blob.get("format_version")
        if version != POLICY_FORMAT_VERSION:
            raise ValueError(
                f"{path}: policy format {version}, this code reads {POLICY_FORMAT_VERSION}"
            )
        model, meta, state = blob["model"], blob["meta"], blob["state_dict"]
    policy = Policy(model)
    policy.load_state_dict(state)
    return policy.eval(), meta
