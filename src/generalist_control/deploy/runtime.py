"""The real-time policy runtime: history buffer, receding horizon, export backends.

:class:`PolicyRuntime` wraps a trained :class:`~generalist_control.model.policy.Policy`. It keeps
its own ``history``-sample buffer of states and references, builds the network's input with
the project's one window builder (:class:`~generalist_control.data.windows.HistoryBuffer`),
and applies the first of the ``horizon`` predicted controls each sample::

    rt = PolicyRuntime.load("models/policy.ckpt")        # or an MLflow URI
    rt.reset("cstr")
    u = rt.step(x, r)                                     # once per dt

On the first step after ``reset`` the buffer is filled with that first sample, exactly as
the window builder pads the start of a training trajectory. A policy trained with
``model.integral`` also sees the integral of the tracking error, which the runtime keeps
exactly as the LQI expert does (``z += dt (r - y)`` after each sample's control, from zero
at ``reset``); ``y`` is the plant's output ``C x`` (rows stored with the policy), or the
measured output passed as ``step(x, r, y)``. Like LQI, such a policy winds up against an
actuator limit; given the limits (:meth:`PolicyRuntime.set_actuator_limits`) the runtime
integrates conditionally, as :class:`~generalist_control.simulation.lqi.AntiWindupLQIController`
does. Many plants can be stepped at once (``reset([...names])`` and ``step`` on
``(B, MAX_ORDER)`` zero-padded states), which is how evaluation batches all plants through
one network call per sample.

Backends: ``"torch"`` (eager), ``"torchscript"`` and ``"onnx"`` (ONNX Runtime); see
:mod:`generalist_control.deploy.export`. In a simulated loop the runtime is driven through
:class:`~generalist_control.deploy.adapter.RuntimeAdapter`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from generalist_control.data.windows import HistoryBuffer
from generalist_control.deploy.export import backend as _backend
from generalist_control.deploy.resolve import resolve
from generalist_control.model.policy import Policy, load_policy
from generalist_control.plants.catalog import available_plants, load_plant
from generalist_control.plants.plant import MAX_ORDER
from generalist_control.simulation.antiwindup import conditional_increment
from generalist_control.simulation.lqi import design_lqi
from generalist_control.simulation.simulate import Perturbation

__all__ = ["PolicyRuntime", "integral_facts"]


class PolicyRuntime:
    """A trained policy stepping one or many plants in a sampled loop.

    Parameters
    ----------
    policy : Policy
    meta : dict
        The policy's metadata: ``tags`` (plant -> tag), ``orders`` (plant -> order),
        ``history``, ``horizon``, ``dt``.
    backend : {"torch", "torchscript", "onnx"}
    """

    def __init__(self, policy: Policy, meta: dict[str, Any], backend: str = "torch") -> None:
        self.policy, self.meta = policy.eval(), meta
        self.tags: dict[str, int] = {str(k): int(v) for k, v in meta["tags"].items()}
        self.orders: dict[str, int] = {str(k): int(v) for k, v in meta["orders"].items()}
        self.history, self.horizon = int(meta["history"]), int(meta["horizon"])
        self.dt = float(meta["dt"])
        self.integral = bool(policy.config.get("integral", 0))
        self.outputs: dict[str, np.ndarray] = {
            str(k): np.asarray(v, dtype=np.float64) for k, v in meta.get("outputs", {}).items()
        }
        #: per plant, the sign of d u / d z of the expert the policy imitates (``-Ki``)
        self.directions: dict[str, float] = {
            str(k): float(v) for k, v in meta.get("integral_directions", {}).items()
        }
        self._unknown: set[str] = set()  # plants neither the meta nor the catalogue knows
        self.limits: Perturbation | None = None
        self.backend = backend
        self._run = _backend(policy, backend)
        self._systems: list[str] = []
        self._single = True
        self.plan = np.zeros((0, self.horizon), np.float32)

    @classmethod
    def load(cls, source: str | Path, backend: str = "torch") -> PolicyRuntime:
        """Load from a policy/checkpoint file or an MLflow URI (see :func:`resolve`)."""
        policy, meta = load_policy(resolve(source))
        return cls(policy, meta, backend)

    @property
    def systems(self) -> list[str]:
        """Plants known to the policy."""
        return sorted(self.tags)

    def reset(self, system: str | Sequence[str]) -> None:
        """Start a new run on ``system`` (a name) or a batch of runs (a list of names)."""
        self._single = isinstance(system, str)
        names = [system] if self._single else [str(s) for s in system]
        for name in names:
            if name not in self.tags:
                raise KeyError(
                    f"unknown plant '{name}' for this policy; it was trained on: "
                    f"{', '.join(self.systems)}"
                )
        self._systems = names
        self._tag = np.array([self.tags[s] for s in names], dtype=np.int64)
        self._order = np.array([self.orders[s] for s in names], dtype=np.int64)
        self._buffer = HistoryBuffer(self._order, self.history, self.integral)
        self._padded = np.zeros((len(names), MAX_ORDER), np.float32)
        self.z = np.zeros(len(names))
        self._u_prev = np.zeros(len(names))
        self._direction: np.ndarray | None = None
        self._C: np.ndarray | None = None
        if self.limits is not None and self.integral:
            self._from_catalogue(names)
            unknown = sorted(set(names) - set(self.directions))
            if unknown:
                raise ValueError(
                    f"anti-windup needs the direction of each plant's integral action; none "
                    f"for {', '.join(unknown)} (not in the policy's meta nor the catalogue)"
                )
            self._direction = np.array([self.directions[n] for n in names])

    def _check(self, x: Any, r: Any) -> tuple[np.ndarray, np.ndarray]:
        if not self._systems:
            raise RuntimeError("call reset(system) before step(x, r)")
        x = np.asarray(x, dtype=np.float64)
        r = np.asarray(r, dtype=np.float64)
        if self._single:
            n = int(self._order[0])
            if x.shape != (n,):
                raise ValueError(
                    f"state has shape {x.shape}; plant '{self._systems[0]}' has {n} states"
                )
            x, r = x[None, :], r.reshape(1)
        else:
            B = len(self._systems)
            if x.ndim != 2 or x.shape[0] != B or x.shape[1] not in (MAX_ORDER, self._order.max()):
                raise ValueError(
                    f"state batch has shape {x.shape}; expected ({B}, {MAX_ORDER}) zero-padded"
                )
            if r.shape != (B,):
                raise ValueError(f"reference batch has shape {r.shape}; expected ({B},)")
        if not (np.isfinite(x).all() and np.isfinite(r).all()):
            raise ValueError("state or reference contains NaN or inf")
        self._padded[:, : x.shape[1]] = x
        return self._padded, r

    def window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The newest window ``(state, mask, ref, tag)`` the policy saw (after a step)."""
        b = self._buffer
        return b.state, b.mask, b.ref, self._tag

    def run_window(
        self, state: np.ndarray, mask: np.ndarray, ref: np.ndarray, tag: np.ndarray
    ) -> np.ndarray:
        """The backend's controls (B, horizon) for raw windows (no history bookkeeping)."""
        return self._run(state, mask, ref, tag)

    def set_actuator_limits(
        self, u_limit: float | None = None, rate_limit: float | None = None
    ) -> None:
        """Known actuator limits for anti-windup of an integrating policy (None: no limit).

        While the actuator clips the command (``|u| <= u_limit``, ``|du/dt| <= rate_limit``)
        the error integral is frozen whenever integrating would push the command further
        into the limit, the direction being that of the LQI expert the policy imitates
        (``-Ki``). Without limits nothing changes. Takes effect at the next :meth:`reset`.
        """
        if u_limit is None and rate_limit is None:
            self.limits = None
        else:
            self.limits = Perturbation(u_limit=u_limit, rate_limit=rate_limit)

    def _from_catalogue(self, names: Sequence[str]) -> None:
        """Output rows and integral directions the policy's meta lacks, from the catalogue."""
        known = set(self.outputs) & set(self.directions)
        missing = sorted(set(names) - known - self._unknown)
        if missing:
            facts = integral_facts(missing)
            for k, v in facts["outputs"].items():
                self.outputs.setdefault(k, np.asarray(v, dtype=np.float64))
            for k, v in facts["integral_directions"].items():
                self.directions.setdefault(k, v)
            self._unknown.update(set(missing) - set(facts["outputs"]))

    def _output_rows(self) -> np.ndarray:
        """``C`` (B, MAX_ORDER) of the current rows, built when ``y`` is first left out."""
        self._from_catalogue(self._systems)
        missing = sorted({s for s in self._systems if s not in self.outputs})
        if missing:
            raise ValueError(
                f"this policy integrates the tracking error but has no output map for "
                f"{', '.join(missing)}: pass the measured output, step(x, r, y)"
            )
        C = np.zeros((len(self._systems), MAX_ORDER))
        for i, name in enumerate(self._systems):
            C[i, : len(self.outputs[name])] = self.outputs[name]
        return C

    def _output(self, y: Any, x: np.ndarray) -> np.ndarray:
        if y is None:
            if self._C is None:
                self._C = self._output_rows()
            return np.einsum("bi,bi->b", self._C, x)  # float64: C is
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        if y.shape != (len(self._systems),):
            raise ValueError(f"output has shape {y.shape}; expected ({len(self._systems)},)")
        if not np.isfinite(y).all():
            raise ValueError("output contains NaN or inf")
        return y

    def _integrate(self, u: np.ndarray, r: np.ndarray, y: np.ndarray) -> None:
        """Advance the error integral after control ``u``, conditionally under known limits."""
        dz = self.dt * (r - y)
        if self._direction is not None and self.limits is not None:
            u_act = self.limits.actuate(u, self._u_prev, self.dt)
            dz = conditional_increment(dz, u, u_act, self._direction)
            self._u_prev = u_act
        self.z = self.z + dz

    def step(self, x: Any, r: Any, y: Any = None) -> float | np.ndarray:
        """Control for the current sample (the first of the predicted sequence).

        Parameters
        ----------
        x : array_like
            State deviation, (n,) for one plant or (B, MAX_ORDER) zero-padded for a batch.
        r : float or array_like
            Reference deviation, scalar or (B,).
        y : float or array_like, optional
            Measured output deviation, for a policy trained with ``model.integral``;
            default ``C x`` with the output rows stored with the policy.
        """
        x, r = self._check(x, r)
        if self.integral:
            y = self._output(y, x)  # checked before anything changes
            state, mask, ref = self._buffer.push(x, r, self.z)
        else:
            state, mask, ref = self._buffer.push(x, r)
        self.plan = self._run(state, mask, ref, self._tag)
        u = self.plan[:, 0].astype(np.float64)
        if self.integral:
            self._integrate(u, r, y)
        return float(u[0]) if self._single else u


def integral_facts(names: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Per catalogue plant in ``names``, its output row ``C`` and the sign of its expert's -Ki.

    What an integrating policy's runtime needs to integrate ``r - C x`` from the state alone
    (``C`` of the linearisation for a nonlinear plant) and to know which way the integral
    moves the command (anti-windup). Training stores them in the policy's meta
    (``outputs``, ``integral_directions``); names the catalogue does not know are left out.
    """
    known = set(available_plants())
    plants = [load_plant(n) for n in sorted(names) if n in known]
    return {
        "outputs": {p.name: [float(c) for c in p.C[0]] for p in plants},
        "integral_directions": {p.name: float(np.sign(-design_lqi(p).Ki)) for p in plants},
    }
