"""The runtime's per-sample path for one plant stepped alone, on plain Python numbers.

:class:`~generalist_control.deploy.runtime.PolicyRuntime` steps one plant (``reset(name)``)
through :class:`OnePlant`: the same checks, window and arithmetic as its general path, with
the limits read once at ``reset`` and the few numbers of a sample handled as Python floats
instead of small arrays. Anything out of the ordinary (an input of another shape or type, a
value out of range, a control or error integral the runtime refuses, known actuator limits)
is left to the general path, which then takes the step or refuses it with its full message:
:meth:`OnePlant.step` returns None before it has changed anything.
"""

from __future__ import annotations

from array import array
from typing import Any

import numpy as np

__all__ = ["OnePlant", "output_of"]

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
    if a.size != 1 or a.dtype.kind not in "fiub":
        return None
    return float(a.reshape(-1)[0])


class OnePlant:
    """:meth:`PolicyRuntime.step` for a runtime reset to one plant (module docstring).

    Parameters
    ----------
    rt : PolicyRuntime
        Reset to one plant by name; this object is rebuilt at each such reset. (Typed
        ``Any`` here: the runtime's module imports this one.)
    """

    def __init__(self, rt: Any) -> None:
        self.rt = rt
        self.n = int(rt._order[0])
        lim = rt._lim
        # at most float32's largest: the state is rounded to float32 (array("f") below)
        self.lim_x: list[float] = np.minimum(lim["state"][0, : self.n], 3.4e38).tolist()
        self.lim_r = float(lim["reference"][0])
        self.lim_u = float(lim["network output"][0, 0])
        self.lim_z = float(lim["error integral"][0]) if rt.integral else 0.0
        self.c: list[float] | None = None  # the output row, read when y is first left out
        self.integral, self.shape, self.plan_shape = rt.integral, (self.n,), (1, rt.horizon)
        self.buffer, self.dt = rt._buffer, rt.dt

    def _output(self, y: Any, xs: list[float]) -> float | None:
        if y is not None:
            yv = _number(y)
            return yv if yv is not None and abs(yv) <= self.lim_r else None
        if self.c is None:
            if self.rt._C is None:
                try:
                    self.rt._C = self.rt._output_rows()  # kept, as the general path does
                except ValueError:
                    return None  # which the general path explains
            self.c = self.rt._C[0, : self.n].tolist()
        return output_of(self.c, xs)

    def step(self, x: Any, r: Any, y: Any = None) -> float | None:
        """The control for this sample, or None (nothing changed: take the general path)."""
        rt = self.rt
        if type(x) is not np.ndarray or x.dtype is not _FLOAT64:
            x = np.asarray(x)
            if x.dtype.kind not in "fiub":
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
        buffer = self.buffer
        state, ref = buffer.stage_one(x, r, z, float(rt._u_prev[0]))
        net = rt._net1
        if net is None or rt._run is not rt._backend:
            net = rt._network
        plan = net(state, ref)
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
        buffer.commit()
        rt.plan = plan.copy()
        return u
