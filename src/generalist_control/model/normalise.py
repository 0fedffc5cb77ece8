"""Per-tag RMS scales of states, reference and controls, fitted on the training windows.

Plants' signals differ by orders of magnitude, so each is divided by its RMS over its own
tag's windows (no offsets: the data are deviations). Unseen tags get the scales over all
windows. With ``mapped``, each tag's plant state is also taken into a frame (``state_map``:
the identity until a plant part's rows set it, as the card's frame does).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from generalist_control.plants.definition import MAX_ORDER

__all__ = ["Normaliser"]

#: Scales below this (a signal that is always zero, or a padded state entry) become one.
_TINY = 1e-12


def _rms(sum_sq: Tensor, count: Tensor) -> Tensor:
    rms = torch.sqrt(sum_sq / count.clamp(min=1))
    return torch.where((count > 0) & (rms > _TINY), rms, torch.ones_like(rms))


#: Windows x tags beyond which sums per tag are scattered rather than taken by a one-hot matrix.
_ONEHOT_LIMIT = 2**27


def _per_tag(tag: Tensor, n_tags: int) -> Callable[[Tensor], Tensor]:
    """Sums of per-window rows per tag: ``(W, ...) -> (n_tags, ...)``."""
    if tag.numel() * n_tags <= _ONEHOT_LIMIT:
        onehot = nn.functional.one_hot(tag, n_tags).to(torch.float64)  # (W, n_tags)
        return lambda v: (onehot.T @ v.reshape(len(v), -1)).reshape(n_tags, *v.shape[1:])
    return lambda v: v.new_zeros((n_tags, *v.shape[1:])).index_add_(0, tag, v)


class Normaliser(nn.Module):
    """Per-tag RMS scales (buffers) of ``n_tags`` tags, windows ``state_dim`` wide.

    ``seen`` flags the tags the scales were fitted on; ``state_map`` (only with ``mapped``)
    takes each tag's padded plant state into the network's frame.
    """

    state_scale: Tensor
    ref_scale: Tensor
    control_scale: Tensor
    seen: Tensor
    state_map: Tensor

    def __init__(self, n_tags: int, state_dim: int, mapped: bool = False) -> None:
        super().__init__()
        self.register_buffer("state_scale", torch.ones(n_tags, state_dim))
        self.register_buffer("ref_scale", torch.ones(n_tags))
        self.register_buffer("control_scale", torch.ones(n_tags))
        self.register_buffer("seen", torch.zeros(n_tags, dtype=torch.bool))
        self.mapped = bool(mapped)
        if self.mapped:
            eye = torch.eye(MAX_ORDER).expand(n_tags, MAX_ORDER, MAX_ORDER)
            self.register_buffer("state_map", eye.clone())

    @torch.no_grad()
    def fit(self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor, target: Tensor) -> None:
        """Set the scales from training windows (``Windows``' fields as tensors).

        Raises
        ------
        ValueError
            If a tag lies outside ``0 .. n_tags - 1`` or there are no windows.
        """
        n_tags = self.seen.numel()
        if tag.numel() == 0:
            raise ValueError("cannot fit the normaliser on zero windows")
        if int(tag.min()) < 0 or int(tag.max()) >= n_tags:
            raise ValueError(
                f"system tags must lie in 0..{n_tags - 1} (model.plant.n_tags = {n_tags}); "
                f"got {int(tag.min())}..{int(tag.max())}"
            )
        d = torch.float64
        m = mask.to(d)
        per_tag = _per_tag(tag, n_tags)
        sx = per_tag(((state.to(d) * m) ** 2).sum(1))  # (n_tags, state_dim)
        cx = per_tag(m.sum(1))
        sr = per_tag((ref.to(d) ** 2).sum(1))
        su = per_tag((target.to(d) ** 2).sum(1))
        n = per_tag(torch.ones(len(tag), dtype=d))
        cr, cu = n * ref.shape[1], n * target.shape[1]
        seen = n > 0
        # unseen tags: the scales over all training windows
        sx[~seen], cx[~seen] = sx.sum(0), cx.sum(0)
        sr[~seen], cr[~seen] = sr.sum(), cr.sum()
        su[~seen], cu[~seen] = su.sum(), cu.sum()
        self.state_scale.copy_(_rms(sx, cx))
        self.ref_scale.copy_(_rms(sr, cr))
        self.control_scale.copy_(_rms(su, cu))
        self.seen.copy_(seen)

    def normalise_inputs(
        self, state: Tensor, mask: Tensor, ref: Tensor, tag: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Scaled ``(state * mask, mask, ref, tag)``; padded entries come out exactly zero."""
        if self.mapped:  # the plant state into its frame, the channels scaled
            x = torch.einsum("bij,btj->bti", self.state_map[tag], state[..., :MAX_ORDER])
            rest = state[..., MAX_ORDER:] / self.state_scale[tag, MAX_ORDER:].unsqueeze(1)
            state = torch.cat([x, rest], dim=-1)
        else:
            state = state / self.state_scale[tag].unsqueeze(1)
        state = state * mask
        ref = ref / self.ref_scale[tag].unsqueeze(1)
        return state, mask, ref, tag

    def normalise_controls(self, u: Tensor, tag: Tensor) -> Tensor:
        """Controls (B, horizon) in plant units -> network units."""
        return u / self.control_scale[tag].unsqueeze(1)

    def denormalise_controls(self, u: Tensor, tag: Tensor) -> Tensor:
        """Network outputs (B, horizon) -> controls in plant units."""
        return u * self.control_scale[tag].unsqueeze(1)
