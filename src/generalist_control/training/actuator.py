"""A random actuator between DAgger's rollouts and their plants (``dagger.sampler.actuator``).

Each rollout row gets a first-order lag and a constant input offset of its own; the windows
keep the *commanded* control (what a deployed policy knows), so the identifier learns to name
a plant whose actuator lags or is offset, as a real one does.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Actuator", "lag_mix"]


def lag_mix(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A first-order lag's mean weight and decay over one sample.

    For a command ``u`` held over a sample from the lag's output ``s`` (time constants
    ``tau`` in samples), the mean output is ``u + mix (s - u)`` and the end value
    ``u + decay (s - u)``: ``decay = exp(-1/tau)``, ``mix = tau (1 - decay)``, 0 at ``tau = 0``.

    Examples
    --------
    >>> mix, decay = lag_mix(np.array([0.0, 0.6]))
    >>> np.round(mix, 3).tolist(), np.round(decay, 3).tolist()
    ([0.0, 0.487], [0.0, 0.189])
    """
    tau = np.asarray(tau, dtype=float)
    safe = np.where(tau > 0, tau, 1.0)
    decay = np.where(tau > 0, np.exp(-1.0 / safe), 0.0)
    return tau * (1.0 - decay), decay


class Actuator:
    """Per row a lag (time constant uniform in ``[0, lag]`` samples) and an offset.

    ``lag`` (rows,) is each row's largest time constant in samples, ``offset`` (rows,) its
    largest input offset in control units (the row's own uniform in ``+-offset``), drawn from
    ``rng``. The lag starts at rest; over a sample the plant receives the lag's mean output
    (:func:`lag_mix`) plus the offset.

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
