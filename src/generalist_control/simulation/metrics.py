"""Step-response and tracking metrics from sampled responses, vectorised over runs.

Relative to the reference's final value ``r_f``, as python-control's ``step_info``; an
undefined metric (never reached, never settled) is NaN.
"""

from __future__ import annotations

import numpy as np

__all__ = ["step_metrics", "tracking_metrics"]


def _first_time(mask: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Time of the first True along the last axis (NaN where none)."""
    return np.where(mask.any(axis=-1), t[np.argmax(mask, axis=-1)], np.nan)


def tracking_metrics(t: np.ndarray, y: np.ndarray, r: np.ndarray) -> dict[str, np.ndarray]:
    """ISE, ITAE and RMSE of ``e = r - y``; ``y``, ``r`` of shape (..., len(t))."""
    e = np.asarray(r, dtype=float) - np.asarray(y, dtype=float)
    return {
        "ISE": np.trapezoid(e**2, t, axis=-1),
        "ITAE": np.trapezoid(t * np.abs(e), t, axis=-1),
        "RMSE": np.sqrt(np.mean(e**2, axis=-1)),
    }


def step_metrics(
    t: np.ndarray,
    y: np.ndarray,
    u: np.ndarray,
    r: np.ndarray,
    settling_threshold: float = 0.02,
    rise_limits: tuple[float, float] = (0.1, 0.9),
) -> dict[str, np.ndarray]:
    """Metrics of step responses ``y`` (..., N) at times ``t`` (N,), controls ``u`` (..., M).

    ``r`` is the reference (..., N) or its final value (...,). Returns ``rise_time``,
    ``overshoot`` (% of ``|r_f|``), ``settling_time``, ``steady_state_error``,
    ``relative_steady_state_error``, ``ISE``, ``ITAE``, ``u_max``; each ``y.shape[:-1]``.
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    r = np.asarray(r, dtype=float)
    r_sig = (
        np.broadcast_to(r[..., None], y.shape) if r.ndim < y.ndim else np.broadcast_to(r, y.shape)
    )
    rf = r_sig[..., -1]
    sgn = np.sign(rf)[..., None]
    lo, hi = rise_limits
    t_lo = _first_time(sgn * (y - lo * rf[..., None]) >= 0, t)
    t_hi = _first_time(sgn * (y - hi * rf[..., None]) >= 0, t)
    with np.errstate(divide="ignore", invalid="ignore"):
        peak = (sgn * y).max(axis=-1)
        overshoot = np.maximum(0.0, 100.0 * (peak - np.abs(rf)) / np.abs(rf))
        outside = np.abs(y / rf[..., None] - 1.0) >= settling_threshold
    n = y.shape[-1]
    last_out = np.where(outside.any(axis=-1), n - 1 - np.argmax(outside[..., ::-1], axis=-1), -1)
    settled = last_out + 1
    settling_time = np.where(settled < n, t[np.minimum(settled, n - 1)], np.nan)
    ess = np.abs(rf - y[..., -1])
    out = {
        "rise_time": t_hi - t_lo,
        "overshoot": np.where(np.isnan(t_hi), np.nan, overshoot),
        "settling_time": settling_time,
        "steady_state_error": ess,
        "relative_steady_state_error": ess / np.abs(rf),
        "u_max": np.abs(np.asarray(u, dtype=float)).max(axis=-1),
    }
    tm = tracking_metrics(t, y, r_sig)
    out["ISE"], out["ITAE"] = tm["ISE"], tm["ITAE"]
    return out
