"""The real-time policy runtime: a trained policy in a sampled control loop.

It keeps each run's window, error integral and last control, and refuses inputs and outputs
outside the policy's range; one plant reset by name steps through a lean path.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np

from generalist_control.data.windows import HistoryBuffer
from generalist_control.deploy.export import backend as _backend
from generalist_control.deploy.one_plant import OnePlantStep, output_of
from generalist_control.deploy.policy_source import resolve
from generalist_control.deploy.refusals import (
    RejectedStep,
    actuator_limit,
    real_array,
    rejection,
    shaped_inputs,
)
from generalist_control.deploy.runtime_plants import (
    GIVEN_TYPES,
    IntegralFacts,
    grown_for,
    plant_of,
    refused_reset,
    unknown_plant,
)
from generalist_control.model.policy import Policy, load_policy
from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.lqi import conditional_increment
from generalist_control.simulation.perturbation import Perturbation

__all__ = ["INPUT_LIMIT", "PolicyRuntime", "RejectedStep"]

#: Default input range of a runtime: each signal at most this many times its training RMS.
INPUT_LIMIT = 1e3

_F = TypeVar("_F", bound=Callable[..., Any])


def _busy_error(method: str) -> RuntimeError:
    return RuntimeError(
        f"PolicyRuntime.{method}: another thread is inside this runtime. A runtime holds one "
        "control loop's state (history, error integral, last control) and serves one thread "
        "at a time: give each thread its own runtime (PolicyRuntime.load again), or "
        "serialise the calls yourself."
    )


def _one_thread(method: _F) -> _F:
    """``method`` refused with a clear error while another thread is inside the runtime."""

    @functools.wraps(method)
    def guarded(self: PolicyRuntime, *args: Any, **kwargs: Any) -> Any:
        if not self._busy.acquire(blocking=False):
            raise _busy_error(method.__name__)
        try:
            return method(self, *args, **kwargs)
        finally:
            self._busy.release()

    return cast(_F, guarded)


class PolicyRuntime:
    """A trained policy stepping one or many plants in a sampled loop.

    Refused (:class:`RejectedStep`, the runtime unchanged), per row with ``s`` the per-tag
    training RMS of the policy's normaliser and ``L = input_limit``: a state entry (padding
    included) ``|x_i| > L s_x[i]``, a reference or measured output ``|r|, |y| > L s_r``, the
    error integral after the sample ``|z| > L s_x[z]``, a predicted control ``|u| > L s_u``;
    NaN and inf always. Inputs are real numbers (else ``TypeError``). One thread at a time (a
    runtime is one loop's state): a call entering while another thread is inside raises
    ``RuntimeError`` and changes nothing.

    Parameters
    ----------
    policy : Policy
    meta : dict
        The policy's metadata: ``tags`` (plant -> tag), ``orders`` (plant -> order),
        ``history``, ``horizon``, ``dt``.
    backend : {"torch", "onnx"}
    input_limit : float
        ``L`` above, a positive number: how many training RMS a signal may reach.
    """

    def __init__(
        self,
        policy: Policy,
        meta: dict[str, Any],
        backend: str = "torch",
        input_limit: float = INPUT_LIMIT,
    ) -> None:
        if not 0.0 < float(input_limit) < np.inf:
            raise ValueError(f"input_limit must be a positive number; got {input_limit!r}")
        self.input_limit = float(input_limit)
        self.policy, self.meta = policy.eval(), meta
        self.tags: dict[str, int] = {str(k): int(v) for k, v in meta["tags"].items()}
        self.orders: dict[str, int] = {str(k): int(v) for k, v in meta["orders"].items()}
        self.history, self.horizon = int(meta["history"]), int(meta["horizon"])
        self.dt = float(meta["dt"])
        self.integral = "integral" in policy.channels
        self.controls = "previous_control" in policy.channels
        self._facts = IntegralFacts(meta)
        self.limits: Perturbation | None = None
        self.backend = backend
        self._backend = _backend(policy, backend)
        self._run: Any = self._backend  # (tests replace it to corrupt the network's output)
        self._plant_run: Any = None  # the backend's batch-1 run of one plant reset by name
        self._one: OnePlantStep | None = None
        self._busy = threading.Lock()
        self._systems: list[str] = []
        self._single = True
        self.plan = np.zeros((0, self.horizon), np.float32)

    @classmethod
    def load(
        cls, source: str | Path, backend: str = "torch", input_limit: float = INPUT_LIMIT
    ) -> PolicyRuntime:
        """Load from a policy/checkpoint file or an MLflow URI (see :func:`resolve`)."""
        policy, meta = load_policy(resolve(source))
        return cls(policy, meta, backend, input_limit)

    @property
    def systems(self) -> list[str]:
        """Plants known to the policy."""
        return sorted(self.tags)

    def _plants(self, system: Any) -> tuple[list[str], bool]:
        """``(names, single)`` of ``reset``'s argument (names, or plants by their model)."""
        single = not isinstance(system, list | tuple | np.ndarray)
        items = [system] if single else list(system)
        if not items or not all(isinstance(s, GIVEN_TYPES) for s in items):
            raise refused_reset(system, self.systems)
        given = [plant_of(s) for s in items]
        names = [s if isinstance(s, str) else self.add_plant(s) for s in given]
        for name in names:
            if name not in self.tags:
                raise unknown_plant(name, self.systems)
        return names, single

    def add_plant(self, plant: Plant) -> str:
        """``plant``'s name; a new one's row added from its model (:func:`.grown_for`)."""
        if plant.name not in self.tags:
            self.policy = grown_for(self.policy, plant, self.dt)
            self._backend = self._run = _backend(self.policy, self.backend)
            self.tags[plant.name] = self.policy.net.n_tags - 1
            self.orders[plant.name] = plant.order
            self._facts.add(plant)
        return plant.name

    @_one_thread
    def reset(self, system: Any) -> None:
        """Start a new run on ``system`` (a plant) or a batch of runs (a list of plants).

        A plant is a name the policy knows, or a plant YAML's path or a model dict.

        Raises
        ------
        TypeError
            If ``system`` is not a plant or a non-empty list of plants (e.g. None, a number).
        KeyError
            If a name is not one of the policy's plants (:attr:`systems`).
        ValueError
            If a plant given by its model cannot be taken (:meth:`add_plant`), or actuator
            limits are known and a plant's integral direction is not.
        """
        names, single = self._plants(system)
        limited = self.limits is not None and self.integral
        direction = self._facts.directions_of(names) if limited else None
        self._single, self._systems, self._direction = single, names, direction
        self._tag = np.array([self.tags[s] for s in names], dtype=np.int64)
        self._order = np.array([self.orders[s] for s in names], dtype=np.int64)
        self._buffer = HistoryBuffer(self._order, self.history, self.integral, self.controls)
        self._padded = np.zeros((len(names), MAX_ORDER), np.float32)
        self.z = np.zeros(len(names))
        self._u_prev = np.zeros(len(names))
        self._C: np.ndarray | None = None
        self._set_limits()
        # one plant by name only: a batch (of one too, as evaluation's) keeps the batch run
        self._plant_run = (
            self._backend.plant(int(self._tag[0]), self._buffer.mask) if single else None
        )
        self._one = OnePlantStep(self) if single else None

    def _set_limits(self) -> None:
        """Per row, the largest magnitude of each input and control (class docstring)."""
        n, L = self.policy.normaliser, self.input_limit
        scales = (n.state_scale, n.ref_scale, n.control_scale)
        sx, sr, su = (s.detach().cpu().double().numpy()[self._tag] for s in scales)
        self._lim = {"state": L * sx[:, :MAX_ORDER]}
        if self.integral:
            self._lim["error integral"] = L * sx[:, MAX_ORDER]
        self._lim["reference"] = self._lim["output"] = L * sr  # y is measured in r's units
        self._lim["network output"] = L * su[:, None]

    @_one_thread
    def select(self, rows: Sequence[int] | np.ndarray) -> None:
        """Go on with only ``rows`` of the batch (in that order), their histories kept."""
        idx = np.asarray(rows, dtype=np.int64).reshape(-1)
        if idx.size == 0 or idx.min() < 0 or idx.max() >= len(self._systems):
            raise ValueError(f"rows must be 1 or more of 0..{len(self._systems) - 1}")
        self._systems = [self._systems[i] for i in idx]
        self._tag, self._order = self._tag[idx], self._order[idx]
        self._buffer.select(idx)
        self._padded = np.zeros((idx.size, MAX_ORDER), np.float32)
        self.z, self._u_prev = self.z[idx], self._u_prev[idx]
        if self._direction is not None:
            self._direction = self._direction[idx]
        if self._C is not None:
            self._C = self._C[idx]
        self.plan = self.plan[idx] if len(self.plan) else self.plan
        self._single = self._single and idx.size == 1
        self._set_limits()
        self._one = OnePlantStep(self) if self._single else None

    def _screen(self, kind: str, values: np.ndarray, limit: np.ndarray) -> None:
        """Refuse the step unless every ``|value| <= limit`` (NaN and inf never are)."""
        ok = np.abs(values) <= limit
        if not ok.all():
            raise rejection(
                kind, values, limit, ok, self._systems, self._order, self._single,
                self.input_limit,
            )  # fmt: skip

    def _check(self, x: Any, r: Any) -> tuple[np.ndarray, np.ndarray]:
        if not self._systems:
            raise RuntimeError("call reset(system) before step(x, r)")
        x, r = shaped_inputs(x, r, self._systems, self._order, self._single)
        self._screen("state", x, self._lim["state"][:, : x.shape[1]])
        self._screen("reference", r, self._lim["reference"])
        self._padded[:, : x.shape[1]] = x
        return self._padded, r

    def window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The newest window ``(state, mask, ref, tag)`` the policy saw (after a step)."""
        b = self._buffer
        return b.state, b.mask, b.ref, self._tag

    @_one_thread
    def set_actuator_limits(
        self, u_limit: float | None = None, rate_limit: float | None = None
    ) -> None:
        """Known actuator limits for anti-windup of an integrating policy (None: no limit).

        The error integral is frozen while integrating would push a clipped command further
        into the limit (the LQI expert's direction, ``-Ki``). Takes effect at :meth:`reset`.

        Raises
        ------
        ValueError
            If a limit is not a positive number (zero, negative or NaN).
        """
        u_limit = actuator_limit(u_limit, "u_limit")
        rate_limit = actuator_limit(rate_limit, "rate_limit")
        if u_limit is None and rate_limit is None:
            self.limits = None
        else:
            self.limits = Perturbation(u_limit=u_limit, rate_limit=rate_limit)

    def _output_rows(self) -> np.ndarray:
        """``C`` (B, MAX_ORDER) of the current rows, built when ``y`` is first left out."""
        if self._C is None:
            self._C = self._facts.output_rows(self._systems)
        return self._C

    def _output(self, y: Any, x: np.ndarray) -> np.ndarray:
        if y is None:
            C = self._output_rows()
            if self._single:  # as OnePlantStep sums it
                return np.array([output_of(C[0].tolist(), x[0].tolist())])
            return np.einsum("bi,bi->b", C, x)  # float64: C is
        y = real_array(y, "measured output y").reshape(-1)
        if y.shape != (len(self._systems),):
            raise ValueError(f"output has shape {y.shape}; expected ({len(self._systems)},)")
        self._screen("output", y, self._lim["output"])
        return y

    def step(self, x: Any, r: Any, y: Any = None) -> float | np.ndarray:
        """Control for the current sample (the first of the predicted sequence).

        A step with a value beyond ``input_limit`` times its training RMS (class docstring)
        is refused whole, nothing changed.

        Parameters
        ----------
        x : array_like
            State deviation, (n,) for one plant or (B, MAX_ORDER) zero-padded for a batch.
        r : float or array_like
            Reference deviation, scalar or (B,).
        y : float or array_like, optional
            Measured output deviation, for a policy with the ``integral`` channel;
            default ``C x`` with the output rows stored with the policy.

        Raises
        ------
        RejectedStep
            If an input, a predicted control or the error integral is out of range.
        TypeError
            If an input is complex.
        """
        if not self._busy.acquire(blocking=False):  # as _one_thread, inline: per sample
            raise _busy_error("step")
        try:  # one plant: the same step on Python numbers, if nothing is unusual
            fast = None if self._one is None else self._one.step(x, r, y)
            return self._step(x, r, y) if fast is None else fast
        finally:
            self._busy.release()

    def _step(self, x: Any, r: Any, y: Any) -> float | np.ndarray:
        """:meth:`step`'s general path."""
        x, r = self._check(x, r)
        if self.integral:
            y = self._output(y, x)  # checked before anything changes
        state, mask, ref = self._buffer.stage(x, r, self.z, self._u_prev)
        plan = np.array(self._network(state, ref))
        if plan.shape != (len(self._systems), self.horizon):
            raise RuntimeError(f"the backend returned controls of shape {plan.shape}")
        self._screen("network output", plan, self._lim["network output"])
        u = plan[:, 0].astype(np.float64)
        # the command as the actuator applies it, and the integral's anti-windup by it
        applied = u if self.limits is None else self.limits.actuate(u, self._u_prev, self.dt)
        if self.integral:
            dz = self.dt * (r - y)
            if self._direction is not None and self.limits is not None:
                dz = conditional_increment(dz, u, applied, self._direction)
            z = self.z + dz
            self._screen("error integral", z, self._lim["error integral"])
            self.z = z
        self._u_prev = applied
        self._buffer.commit()
        self.plan = plan
        return float(u[0]) if self._single else u

    def _network(self, state: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """The backend's controls for the staged window (its batch-1 run for one plant)."""
        if self._plant_run is not None and self._run is self._backend:
            return self._plant_run(state, ref)
        return np.asarray(self._run(state, self._buffer.mask, ref, self._tag))

    @_one_thread
    def record_applied(self, u: Any) -> None:
        """Tell the runtime the control the plant received at the last :meth:`step`.

        Where another controller's control replaced the runtime's own: the
        ``previous_control`` channel and a known rate limit start from it. ``u``: a scalar
        for one plant, (B,) for a batch; finite.
        """
        u = real_array(u, "applied control u").reshape(-1)
        if u.shape != self._u_prev.shape:
            raise ValueError(
                f"applied control has shape {u.shape}; expected {self._u_prev.shape} "
                "(one per running plant)"
            )
        if not np.all(np.isfinite(u)):
            rows = np.flatnonzero(~np.isfinite(u)).tolist()
            raise ValueError(f"applied control is not finite in rows {rows}")
        self._u_prev = u.copy()
