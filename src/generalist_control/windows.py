"""The one window builder shared by training, evaluation and deployment.

A window at sample ``k`` holds the last ``history`` samples ``k - history + 1 .. k`` of the
state (zero-padded to :data:`~generalist_control.plants.MAX_ORDER` and masked) and of the
reference, the plant's tag, and, for training, the next ``horizon`` expert controls
``u[k] .. u[k + horizon - 1]``. Before the first sample the history repeats the first
sample (the runtime fills its buffer the same way on its first step), so every sample
``k = 0 .. N - horizon`` of a trajectory of ``N`` samples yields a window.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from generalist_control.plants import MAX_ORDER

__all__ = [
    "HistoryBuffer",
    "Windows",
    "build_windows",
    "history_windows",
    "pad_states",
    "validity_mask",
    "windows_per_trajectory",
]


@dataclass(frozen=True)
class Windows:
    """Policy inputs (and targets) for ``W`` windows.

    Attributes
    ----------
    state, mask : ndarray, float32, shape (W, history, MAX_ORDER)
        Masked, zero-padded state history and its validity mask.
    ref : ndarray, float32, shape (W, history)
    tag : ndarray, int64, shape (W,)
    target : ndarray, float32, shape (W, horizon), or None at deployment
    traj : ndarray, int64, shape (W,)
        Index of the trajectory each window comes from (for splits by trajectory).
    """

    state: np.ndarray
    mask: np.ndarray
    ref: np.ndarray
    tag: np.ndarray
    target: np.ndarray | None
    traj: np.ndarray

    def __len__(self) -> int:
        return self.state.shape[0]


def windows_per_trajectory(n_samples: int, horizon: int) -> int:
    """Windows cut from one trajectory of ``n_samples`` samples."""
    return max(0, n_samples - horizon + 1)


def pad_states(x: np.ndarray) -> np.ndarray:
    """Zero-pad the last axis of ``x`` (..., n) to ``MAX_ORDER``."""
    n = x.shape[-1]
    if n > MAX_ORDER:
        raise ValueError(f"state has {n} entries; at most {MAX_ORDER} are supported")
    out = np.zeros((*x.shape[:-1], MAX_ORDER), dtype=x.dtype)
    out[..., :n] = x
    return out


def history_windows(
    x: np.ndarray, r: np.ndarray, order: np.ndarray, history: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """State, mask and reference histories ending at every sample.

    Parameters
    ----------
    x : ndarray, shape (B, N, MAX_ORDER)
        Zero-padded states of ``B`` trajectories.
    r : ndarray, shape (B, N)
    order : ndarray of int, shape (B,)
        Number of real state entries of each trajectory.
    history : int

    Returns
    -------
    state, mask : ndarray, float32, shape (B, N, history, MAX_ORDER)
    ref : ndarray, float32, shape (B, N, history)
    """
    x = np.asarray(x, dtype=np.float32)
    r = np.asarray(r, dtype=np.float32)
    front = history - 1
    xp = np.concatenate([np.repeat(x[:, :1], front, axis=1), x], axis=1)
    rp = np.concatenate([np.repeat(r[:, :1], front, axis=1), r], axis=1)
    state = np.moveaxis(sliding_window_view(xp, history, axis=1), -1, 2)
    ref = sliding_window_view(rp, history, axis=1)
    valid = validity_mask(order)
    mask = np.broadcast_to(valid[:, None, None, :], state.shape)
    return state * mask, mask, ref


def validity_mask(order: np.ndarray) -> np.ndarray:
    """Float32 (B, MAX_ORDER): one for the real state entries of each order, zero for padding."""
    return (np.arange(MAX_ORDER) < np.asarray(order)[:, None]).astype(np.float32)


class HistoryBuffer:
    """The newest ``history`` samples of ``B`` running trajectories, for online stepping.

    Gives, at every sample, exactly the last window :func:`history_windows` would build
    from the whole trajectory so far (the first sample repeated in front until the history
    is full), without rebuilding it: the deployment path of the one window builder.

    Parameters
    ----------
    order : ndarray of int, shape (B,)
    history : int
    """

    def __init__(self, order: np.ndarray, history: int) -> None:
        self.mask = np.ascontiguousarray(
            np.broadcast_to(validity_mask(order)[:, None, :], (len(order), history, MAX_ORDER))
        )
        self.state = np.zeros((len(order), history, MAX_ORDER), np.float32)
        self.ref = np.zeros((len(order), history), np.float32)
        self._empty = True

    def push(self, x: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Append zero-padded states ``x`` (B, MAX_ORDER) and references ``r`` (B,).

        Returns the newest window ``(state, mask, ref)``: float32 (B, history, MAX_ORDER),
        (B, history, MAX_ORDER) and (B, history); the state is masked.
        """
        x = x * self.mask[:, 0]
        if self._empty:
            self.state[:] = x[:, None, :]
            self.ref[:] = r[:, None]
            self._empty = False
        else:
            self.state[:, :-1] = self.state[:, 1:]
            self.ref[:, :-1] = self.ref[:, 1:]
            self.state[:, -1], self.ref[:, -1] = x, r
        return self.state, self.mask, self.ref


def build_windows(
    x: np.ndarray,
    r: np.ndarray,
    u: np.ndarray,
    tag: np.ndarray,
    order: np.ndarray,
    history: int,
    horizon: int,
) -> Windows:
    """Training windows from ``B`` trajectories of ``N`` samples.

    Parameters
    ----------
    x : ndarray, shape (B, N, MAX_ORDER)
        Zero-padded states at each sample.
    r, u : ndarray, shape (B, N)
        Reference and expert control at each sample.
    tag, order : ndarray of int, shape (B,)
    history, horizon : int

    Returns
    -------
    Windows
        ``B * (N - horizon + 1)`` windows, trajectory-major.
    """
    B, N = r.shape
    keep = windows_per_trajectory(N, horizon)
    state, mask, ref = history_windows(x, r, order, history)
    target = sliding_window_view(np.asarray(u, dtype=np.float32), horizon, axis=1)
    W = B * keep
    return Windows(
        state=np.ascontiguousarray(state[:, :keep]).reshape(W, history, MAX_ORDER),
        mask=np.ascontiguousarray(mask[:, :keep]).reshape(W, history, MAX_ORDER),
        ref=np.ascontiguousarray(ref[:, :keep]).reshape(W, history),
        tag=np.repeat(np.asarray(tag, dtype=np.int64), keep),
        target=np.ascontiguousarray(target[:, :keep]).reshape(W, horizon),
        traj=np.repeat(np.arange(B, dtype=np.int64), keep),
    )
