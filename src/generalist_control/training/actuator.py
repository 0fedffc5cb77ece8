"""An actuator that is not the model's, between DAgger's rollouts and their plants.

``dagger.sampler.actuator`` (sim-to-real without the tag): each rollout row gets a
first-order lag and a constant input disturbance of its own, drawn at random, between the
control the policy commands and the control the plant receives. The policy's windows keep
the *commanded* control (the one a deployed policy knows), the experts label what they
would command, and the identifier learns to name a plant whose actuator lags or is offset
(a motor's time constant, a heavier vehicle's unbalanced weight), as a real one does. The
plants in the data are untouched.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Actuator", "lag_mix"]


def lag_mix(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A first-order lag's mean weight and decay over one sample.

    Parameters
    ----------
    tau : ndarray
        Time constants in sample periods (>= 0).

    Returns
    -------
    mix, decay : ndarray
        Holding the command ``u`` over a sample that starts at the lag's output ``s``, the
        output's mean over the sample is ``u + mix (s - u)`` and its end value
        ``u + decay (s - u)``: ``decay = exp(-1/tau)``, ``mix = tau (1 - decay)``; both 0
        at ``tau = 0`` (no lag).

    Examples
    --------
    >>> mix, decay = lag_mix(np.array([0.0, 0.6]))
    >>> np.round(mix, 3).tolist(), np.round(decay, 3).tolist()
    ([0.0, 0.488], [0.0, 0.189])
    """
    tau = np.asarray(tau, dtype=float)
    safe = np.where(tau > 0, tau, 1.0)
    decay = np.where(tau > 0, np.exp(-1.0 / safe), 0.0)
    return tau * (1.0 - decay), decay


class Actuator:
    """Per row a lag (time constant uniform in ``[0, lag]`` samples) and an offset.

    Parameters
    ----------
    lag : ndarray, shape (rows,)
        Each row's largest time constant, in sample periods (0: no lag).
    offset : ndarray, shape (rows,)
        Each row's largest constant input disturbance, in its plant's control units; the
        row's own is uniform in ``[-offset, offset]``.
    rng : numpy.random.Generator
        Draws the rows' time constants, then their offsets.

    Notes
    -----
    The lag starts at rest (output 0, as the plant does). Over a sample the plant receives
    the lag's mean output (:func:`lag_mix`) plus the offset, held over the sample.

    Examples
    --------
    >>> act = Actuator(np.zeros(2), np.zeros(2), np.random.default_rng(0))
    >>> act(np.array([1.0, -2.0])).tolist()
    [1.0, -2.0]
    """

    def __init__(self, lag: np.ndarray, offset: np.ndarray, rng: np.random.Generator) -> None:
        lag, offset = np.asarray(lag, dtype=float), np.asarray(offset, dtype=float)
        if lag.shape != offset.shape or lag.ndim != 1:
            raise ValueError(f"lag {lag.shape} and offset {offset.shape} must be (rows,) alike")
        for name, v in (("lag", lag), ("offset", offset)):
            if not np.all(np.isfinite(v) & (v >= 0)):
                raise ValueError(f"the actuator's {name} must be finite and >= 0, got {v}")
        self.tau = lag * rng.random(lag.shape[0])
        self.d = offset * rng.uniform(-1.0, 1.0, offset.shape[0])
        self.mix, self.decay = lag_mix(self.tau)
        self.s = np.zeros(lag.shape[0])

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """What the plants receive over this sample for commands ``u`` (rows,)."""
        u = np.asarray(u, dtype=float)
        applied = u + self.mix * (self.s - u) + self.d
        self.s = u + self.decay * (self.s - u)
        return applied
