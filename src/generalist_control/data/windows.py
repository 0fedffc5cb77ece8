"""The one window builder shared by training, evaluation and deployment.

A window at sample ``k`` holds samples ``k - history + 1 .. k`` (the first repeated before a
start) of the masked state, optional error integral and previous control, and reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from generalist_control.plants.definition import MAX_ORDER

__all__ = [
    "HistoryBuffer",
    "Windows",
    "build_windows",
    "history_windows",
    "integral_of_error",
    "previous_controls",
    "validity_mask",
    "windows_per_trajectory",
]


@dataclass(frozen=True)
class Windows:
    """Policy inputs (and targets) for ``W`` windows.

    ``state``, ``mask`` (W, history, width): ``MAX_ORDER`` channels, then the error integral
    and the previous control if kept; ``target`` (W, horizon) is None at deployment; ``traj``
    is each window's trajectory (for splits by trajectory).
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


def integral_of_error(r: np.ndarray, y: np.ndarray, dt: float) -> np.ndarray:
    """The LQI expert's forward-Euler error integral (B, N, float64) before each control."""
    r = np.asarray(r, dtype=np.float64)
    inc = float(dt) * (r - np.asarray(y, dtype=np.float64))
    z = np.zeros_like(r)
    if r.shape[1] > 1:
        z[:, 1:] = np.cumsum(inc[:, :-1], axis=1)
    return z


def previous_controls(u: np.ndarray) -> np.ndarray:
    """The control applied one sample earlier: ``u[:, k - 1]``, zero at ``k = 0`` (float64)."""
    u = np.asarray(u, dtype=np.float64)
    prev = np.zeros_like(u)
    prev[:, 1:] = u[:, :-1]
    return prev


def history_windows(
    x: np.ndarray,
    r: np.ndarray,
    order: np.ndarray,
    history: int,
    z: np.ndarray | None = None,
    u_prev: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """State, mask (B, N, history, width) and reference histories ending at every sample.

    ``x`` (B, N, MAX_ORDER) are zero-padded states with ``order`` real entries; ``z`` and
    ``u_prev`` (B, N), if given, are appended as channels.
    """
    extra = [np.asarray(c)[..., None] for c in (z, u_prev) if c is not None]
    if extra:
        x = np.concatenate([np.asarray(x), *extra], axis=-1)
    x = np.asarray(x, dtype=np.float32)
    r = np.asarray(r, dtype=np.float32)
    front = history - 1
    xp = np.concatenate([np.repeat(x[:, :1], front, axis=1), x], axis=1)
    rp = np.concatenate([np.repeat(r[:, :1], front, axis=1), r], axis=1)
    state = np.moveaxis(sliding_window_view(xp, history, axis=1), -1, 2)
    ref = sliding_window_view(rp, history, axis=1)
    valid = validity_mask(order, integral=z is not None, controls=u_prev is not None)
    mask = np.broadcast_to(valid[:, None, None, :], state.shape)
    return state * mask, mask, ref


def validity_mask(order: np.ndarray, integral: bool = False, controls: bool = False) -> np.ndarray:
    """Float32 (B, width): one for the real state entries and the channels, zero for padding."""
    valid = np.arange(MAX_ORDER) < np.asarray(order)[:, None]
    extra = int(integral) + int(controls)
    if extra:
        valid = np.concatenate([valid, np.ones((valid.shape[0], extra), bool)], axis=1)
    return valid.astype(np.float32)


class HistoryBuffer:
    """The newest ``history`` samples of ``B`` running trajectories, for online stepping.

    Exactly the last window :func:`history_windows` would build so far. :meth:`stage` builds
    the next window into preallocated arrays and :meth:`commit` keeps it (a caller can drop
    a failed one).
    """

    def __init__(
        self, order: np.ndarray, history: int, integral: bool = False, controls: bool = False
    ) -> None:
        valid = validity_mask(order, integral, controls)
        self.integral, self.controls = bool(integral), bool(controls)
        self.mask = np.ascontiguousarray(
            np.broadcast_to(valid[:, None, :], (len(order), history, valid.shape[1]))
        )
        self.state = np.zeros(self.mask.shape, np.float32)
        self.ref = np.zeros((len(order), history), np.float32)
        self._next_state, self._next_ref = np.zeros_like(self.state), np.zeros_like(self.ref)
        self._empty, self._staged = True, False
        self._views: tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]] | None = None

    def stage(
        self,
        x: np.ndarray,
        r: np.ndarray,
        z: np.ndarray | None = None,
        u_prev: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The window :meth:`push` would return (valid until the next), the buffer unchanged."""
        if self.integral and z is None:
            raise ValueError("this buffer keeps the error integral: push(x, r, z)")
        if self.controls and u_prev is None:
            raise ValueError("this buffer keeps the previous control: push(x, r, z, u_prev)")
        state, ref = self._next_state, self._next_ref
        row = state[:, -1]  # a view: written in place, this runs once per sample
        row[:, : x.shape[1]] = x
        if z is not None and self.integral:
            row[:, MAX_ORDER] = z
        if u_prev is not None and self.controls:
            row[:, -1] = u_prev
        np.multiply(row, self.mask[:, 0], out=row)
        if self._empty:
            state[:, :-1] = row[:, None, :]
            ref[:] = r[:, None]
        else:
            state[:, :-1] = self.state[:, 1:]
            ref[:, :-1] = self.ref[:, 1:]
            ref[:, -1] = r
        self._staged = True
        return state, self.mask, ref

    def stage_one(
        self, x: np.ndarray, r: float, z: float = 0.0, u_prev: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`stage` for one trajectory from its real states ``x`` (n,), unchecked."""
        (shift, older, row_x, row, ref_shift, ref_older, ref_row), _ = (
            self._views or self._one_views()
        )
        row_x[:] = x  # the padding of this row is zero and is never written
        if self.integral:
            row[MAX_ORDER] = z
        if self.controls:
            row[-1] = u_prev
        if self._empty:
            self._next_state[0, :-1] = row
            ref_row[:] = r
        else:
            shift[:] = older  # the samples but the oldest, one sample earlier
            ref_shift[:] = ref_older
            ref_row[-1] = r
        self._staged = True
        return self._next_state, self._next_ref

    def _one_views(self) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
        """Views :meth:`stage_one` writes through, one per set of arrays, made once."""
        order = int(self.mask[0, 0, :MAX_ORDER].sum())
        w = self.mask.shape[-1]

        def into(
            state: np.ndarray, ref: np.ndarray, src: np.ndarray, src_ref: np.ndarray
        ) -> tuple[np.ndarray, ...]:
            return (state.reshape(-1)[:-w], src.reshape(-1)[w:], state[0, -1, :order],
                    state[0, -1], ref[0, :-1], src_ref[0, 1:], ref[0])  # fmt: skip

        self._views = (
            into(self._next_state, self._next_ref, self.state, self.ref),
            into(self.state, self.ref, self._next_state, self._next_ref),
        )
        return self._views

    def commit(self) -> None:
        """Make the window of the last :meth:`stage` the newest (swaps arrays, copies none)."""
        if not self._staged:
            raise RuntimeError("nothing staged: call stage(x, r) before commit()")
        self.state, self._next_state = self._next_state, self.state
        self.ref, self._next_ref = self._next_ref, self.ref
        self._empty = self._staged = False
        if self._views is not None:
            self._views = (self._views[1], self._views[0])

    def push(
        self,
        x: np.ndarray,
        r: np.ndarray,
        z: np.ndarray | None = None,
        u_prev: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Append one sample of states ``x`` (B, MAX_ORDER) and ``r``, ``z``, ``u_prev`` (B,)."""
        self.stage(x, r, z, u_prev)
        self.commit()
        return self.state, self.mask, self.ref

    def select(self, rows: np.ndarray) -> None:
        """Keep only ``rows`` (indices, in the order given) of the batch, their history kept."""
        rows = np.asarray(rows, dtype=np.int64)
        self.mask = np.ascontiguousarray(self.mask[rows])
        self.state, self.ref = self.state[rows], self.ref[rows]
        self._next_state, self._next_ref = np.zeros_like(self.state), np.zeros_like(self.ref)
        self._staged = False
        self._views = None


def build_windows(
    x: np.ndarray,
    r: np.ndarray,
    u: np.ndarray,
    tag: np.ndarray,
    order: np.ndarray,
    history: int,
    horizon: int,
    z: np.ndarray | None = None,
    controls: bool = False,
) -> Windows:
    """``B * (N - horizon + 1)`` training windows, trajectory-major, of ``B`` trajectories.

    ``u`` (B, N) are the expert's controls; ``z`` the error integral and ``controls`` the
    previous control as channels (:func:`history_windows`).
    """
    B, N = r.shape
    keep = windows_per_trajectory(N, horizon)
    u_prev = previous_controls(u) if controls else None
    state, mask, ref = history_windows(x, r, order, history, z, u_prev)
    target = sliding_window_view(np.asarray(u, dtype=np.float32), horizon, axis=1)
    W = B * keep
    width = state.shape[-1]
    return Windows(
        state=np.ascontiguousarray(state[:, :keep]).reshape(W, history, width),
        mask=np.ascontiguousarray(mask[:, :keep]).reshape(W, history, width),
        ref=np.ascontiguousarray(ref[:, :keep]).reshape(W, history),
        tag=np.repeat(np.asarray(tag, dtype=np.int64), keep),
        target=np.ascontiguousarray(target[:, :keep]).reshape(W, horizon),
        traj=np.repeat(np.arange(B, dtype=np.int64), keep),
    )
