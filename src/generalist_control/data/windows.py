"""The one window builder shared by training, evaluation and deployment.

A window at sample ``k`` holds samples ``k - history + 1 .. k`` of the zero-padded, masked
state and of the reference, and for training the next ``horizon`` expert controls. Optional
channels after the state: the error integral (the LQI expert's own integrator, so the window
holds its ``[x; z]``) and the previous control. The first sample is repeated before a start.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from generalist_control.plants.plant import MAX_ORDER

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

    Attributes
    ----------
    state, mask : ndarray, float32, shape (W, history, width)
        Masked, zero-padded state history and its validity mask; ``width`` is
        ``MAX_ORDER``, plus one with the error integral (channel ``MAX_ORDER``), plus one
        with the previous control (the last channel).
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


def integral_of_error(r: np.ndarray, y: np.ndarray, dt: float) -> np.ndarray:
    """The LQI expert's forward-Euler error integrator (B, N) before each sample's control.

    ``z[:, 0] = 0``, ``z[:, k] = z[:, k - 1] + dt (r[:, k - 1] - y[:, k - 1])`` in float64,
    in :class:`~generalist_control.simulation.lqi.LQIController`'s order; ``r``, ``y`` (B, N).
    """
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
    """State, mask and reference histories ending at every sample.

    Parameters
    ----------
    x : ndarray, shape (B, N, MAX_ORDER)
        Zero-padded states of ``B`` trajectories.
    r : ndarray, shape (B, N)
    order : ndarray of int, shape (B,)
        Number of real state entries of each trajectory.
    z : ndarray, shape (B, N), optional
        Error integral (:func:`integral_of_error`), appended as a state channel.
    u_prev : ndarray, shape (B, N), optional
        Previous controls (:func:`previous_controls`), appended as the last channel.

    Returns
    -------
    state, mask : ndarray, float32, shape (B, N, history, width)
        ``width`` is ``MAX_ORDER``, plus one for each of ``z`` and ``u_prev`` given.
    ref : ndarray, float32, shape (B, N, history)
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

    At every sample, exactly the last window :func:`history_windows` would build from the
    trajectory so far: the deployment path of the one window builder. :meth:`stage` builds
    the window :meth:`push` would give and :meth:`commit` keeps it, so a caller can drop a
    window on failure; both write into preallocated arrays, swapped on commit. ``integral``
    and ``controls`` keep those channels (``push(x, r, z, u_prev)``).
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
        # stage_one's views of the two sets of arrays (_one_views)
        self._views: tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]] | None = None

    def stage(
        self,
        x: np.ndarray,
        r: np.ndarray,
        z: np.ndarray | None = None,
        u_prev: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The window :meth:`push` would return, leaving the buffer as it is.

        Valid until the next :meth:`stage` or :meth:`push`; :meth:`commit` makes it the
        buffer's newest window.
        """
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
        """:meth:`stage` for a buffer of one trajectory from plain numbers, unchecked.

        ``x`` (n,): the real states only (the padding stays zero). Returns ``(state, ref)``.
        """
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
        """Append states ``x`` (B, MAX_ORDER), references ``r``, integrals ``z``, ``u_prev`` (B,).

        Returns the newest window ``(state, mask, ref)``, float32, the state masked.
        """
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
    """Training windows from ``B`` trajectories of ``N`` samples.

    Parameters
    ----------
    x : ndarray, shape (B, N, MAX_ORDER)
        Zero-padded states at each sample.
    r, u : ndarray, shape (B, N)
        Reference and expert control at each sample.
    z : ndarray, shape (B, N), optional
        Error integral (:func:`integral_of_error`), a state channel when given.
    controls : bool
        The previous control (:func:`previous_controls` of ``u``) is the last channel.

    Returns
    -------
    Windows
        ``B * (N - horizon + 1)`` windows, trajectory-major.
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
