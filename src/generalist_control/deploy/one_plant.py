"""The runtime's per-sample path for one plant stepped alone, on plain Python numbers.

Each small NumPy operation costs about a network layer; anything unusual returns None before
anything changed, and the general path takes the step or refuses it.
"""

from __future__ import annotations

from array import array
from typing import Any

import numpy as np

__all__ = ["OnePlantStep", "output_of"]

_FLOAT64 = np.dtype(np.float64)


def output_of(c: list[float], x: list[float]) -> float:
    """``y = C x`` for one plant, summed in the order of the states (float64)."""
    y = 0.0
    for ci, xi in zip(c, x, strict=False):
        y += ci * xi
    return y


def _number(value: Any) -> float | None:
    """A real scalar as a float, or None (the general path will say what is wrong)."""
    if type(value) is float:
        return value
    a = np.asarray(value)
    if a.size != 1 or a.dtype.kind not in "fiu":
        return None
    return float(a.reshape(-1)[0])


class OnePlantStep:
    """:meth:`PolicyRuntime.step` of runtime ``rt`` (``Any``: its module imports this one)."""

    def __init__(self, rt: Any) -> None:
        self.rt, self.buffer, self.dt, self.integral = rt, rt._buffer, rt.dt, rt.integral
        n, lim = int(rt._order[0]), rt._lim
        # at most float32's largest: the state is rounded to float32 in the window
        self.lim_x: list[float] = np.minimum(lim["state"][0, :n], 3.4e38).tolist()
        self.lim_r = float(lim["reference"][0])
        self.lim_u = float(lim["network output"][0, 0])
        self.lim_z = float(lim["error integral"][0]) if rt.integral else 0.0
        self.c: list[float] | None = None  # the output row, read when y is first left out
        self.shape, self.plan_shape = (n,), (1, rt.horizon)

    def _output(self, y: Any, xs: list[float]) -> float | None:
        if y is not None:
            yv = _number(y)
            return yv if yv is not None and abs(yv) <= self.lim_r else None
        if self.c is None:
            try:
                self.c = self.rt._output_rows()[0, : self.shape[0]].tolist()
            except ValueError:
                return None  # which the general path explains
        return output_of(self.c, xs)

    def step(self, x: Any, r: Any, y: Any = None) -> float | None:
        """The control for this sample, or None (nothing changed: take the general path)."""
        rt = self.rt
        if type(x) is not np.ndarray or x.dtype is not _FLOAT64:
            x = np.asarray(x)
            if x.dtype.kind not in "fiu":
                return None
            x = x.astype(np.float64)
        if type(r) is not float:
            r = _number(r)
        if x.shape != self.shape or r is None or rt.limits is not None or not abs(r) <= self.lim_r:
            return None
        xs = x.tolist()
        for v, limit in zip(xs, self.lim_x, strict=True):
            if not abs(v) <= limit:
                return None
        z = float(rt.z[0]) if self.integral else 0.0
        if self.integral:
            # y = C x of the state as the window holds it (float32), as the general path
            yv = self._output(y, array("f", xs).tolist())
            if yv is None:
                return None
        state, ref = self.buffer.stage_one(x, r, z, float(rt._u_prev[0]))
        plan = (rt._plant_run if rt._run is rt._backend else rt._network)(state, ref)
        if plan.shape != self.plan_shape:
            return None
        ps = plan.tolist()[0]
        for v in ps:
            if not abs(v) <= self.lim_u:
                return None
        if self.integral:
            z = z + self.dt * (r - yv)
            if not abs(z) <= self.lim_z:
                return None
            rt.z[0] = z
        rt._u_prev[0] = u = ps[0]
        self.buffer.commit()
        rt.plan = plan.copy()
        return u
