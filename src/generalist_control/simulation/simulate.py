"""Closed-loop simulation of plants under any controllers, in one sampled loop.

Linear plants advance by the exact zero-order hold, nonlinear ones by RK4; ``u[k]`` is held.
:func:`simulate_stacked` runs many batches (plants, controllers, lengths) together;
:func:`simulate_many` and :func:`simulate` are its one-controller cases.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.linalg import expm

from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.perturbation import Perturbation, RowPerturbations

__all__ = [
    "BatchController",
    "Controller",
    "PerPlantController",
    "Run",
    "Segment",
    "Trajectory",
    "controller_rows",
    "discretise",
    "plant_stepper",
    "rk4",
    "row_slices",
    "simulate",
    "simulate_many",
    "simulate_stacked",
]

#: A state whose magnitude exceeds this is treated as diverged.
DIVERGENCE_BOUND = 1e6


class Controller(Protocol):
    """What the simulator drives: batched, stateful, one call per sample."""

    def reset(self, batch_size: int) -> None:
        """Clear internal state before ``batch_size`` parallel runs."""

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls ``(batch,)`` for states ``(batch, n)`` and references ``(batch,)``."""


@dataclass(frozen=True)
class Trajectory:
    """A batch of closed-loop runs in deviation coordinates: ``x`` (batch, N + 1, n), ``y``.

    ``u`` (batch, N) is the delivered control (before any disturbance); a ``diverged`` run
    (non-finite or beyond ``DIVERGENCE_BOUND``) is frozen at its last finite state.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    r: np.ndarray
    y: np.ndarray
    diverged: np.ndarray


def discretise(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation via the block matrix exponential (cached)."""
    A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
    Ad, Bd = _discretise(A.tobytes(), B.tobytes(), B.shape, float(dt))
    return Ad.copy(), Bd.copy()


@functools.lru_cache(maxsize=512)
def _discretise(
    a: bytes, b: bytes, shape: tuple[int, int], dt: float
) -> tuple[np.ndarray, np.ndarray]:
    n, m = shape
    M = np.zeros((n + m, n + m))
    M[:n, :n] = np.frombuffer(a).reshape(n, n)
    M[:n, n:] = np.frombuffer(b).reshape(n, m)
    E = expm(M * dt)
    return E[:n, :n], E[:n, n:]


def rk4(
    deriv: Callable[[np.ndarray], np.ndarray], x: np.ndarray, h: float, substeps: int
) -> np.ndarray:
    """``substeps`` classic Runge-Kutta steps of length ``h`` of ``dx/dt = deriv(x)``."""
    for _ in range(substeps):
        k1 = deriv(x)
        k2 = deriv(x + 0.5 * h * k1)
        k3 = deriv(x + 0.5 * h * k2)
        k4 = deriv(x + h * k3)
        x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def plant_stepper(plant: Plant) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``advance(x, u) -> x_next``: one sample of ``plant`` unperturbed (ZOH or RK4), batched."""
    if plant.is_linear:
        Ad, Bd = discretise(plant.A, plant.B, plant.dt)
        return lambda x, u: x @ Ad.T + u[:, None] * Bd[:, 0]
    h = plant.dt / plant.substeps
    return lambda x, u: rk4(lambda s: plant.deriv(s, u), x, h, plant.substeps)


@dataclass(frozen=True)
class Run:
    """A batch of runs on one plant for :func:`simulate_many`."""

    plant: Plant
    r: np.ndarray
    x0: np.ndarray | None = None
    perturbation: Perturbation | None = None


class BatchController(Protocol):
    """A controller of many plants at once (the learned policy, or LQI experts stacked)."""

    def reset(self, plants: Sequence[Plant], counts: Sequence[int]) -> None:
        """Prepare for ``counts[i]`` runs of ``plants[i]``, stacked in that order."""

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Controls ``(B,)`` for zero-padded states ``(B, MAX_ORDER)`` and references."""


def row_slices(counts: Sequence[int]) -> list[slice]:
    """The rows of each group when ``counts[i]`` runs of group ``i`` are stacked in order."""
    ends = np.cumsum([0, *counts])
    return [slice(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:], strict=True)]


class PerPlantController:
    """A :class:`BatchController` of one ``make(plant)`` controller per group of rows."""

    def __init__(self, make: Callable[[Plant], Controller]) -> None:
        self.make = make
        self._parts: list[tuple[Controller, int, slice]] = []

    def reset(self, plants: Sequence[Plant], counts: Sequence[int]) -> None:
        """Build and reset one controller per plant."""
        self._parts = []
        for plant, count, rows in zip(plants, counts, row_slices(counts), strict=True):
            ctrl = self.make(plant)
            ctrl.reset(count)
            self._parts.append((ctrl, plant.order, rows))

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Route each group's rows (unpadded) to its controller."""
        u = np.empty(x.shape[0])
        for ctrl, n, rows in self._parts:
            u[rows] = ctrl.step(x[rows, :n], r[rows])
        return u


@dataclass(frozen=True)
class Segment:
    """Runs one batch controller drives, reset with the segment's distinct plants' rows.

    Ended runs' rows are commanded NaN; an optional ``finish(rows)`` is told which rows ended.
    """

    controller: BatchController
    runs: Sequence[Run]


class _Layout:
    """Where every run's rows lie: grouped by plant, then segment, then run."""

    def __init__(self, segments: Sequence[Segment]) -> None:
        # by identity (a variant is another plant of the same name)
        plants = list({id(run.plant): run.plant for seg in segments for run in seg.runs}.values())
        self.plants = plants
        self.rows: dict[tuple[int, int], slice] = {}  # per (segment, run): global rows
        self.local: dict[tuple[int, int], slice] = {}  # and its rows in its segment's batch
        # a linear plant's update per segment: BLAS's path depends on the number of rows
        self.blocks: list[tuple[Plant, slice]] = []
        order: list[list[int]] = [[] for _ in segments]
        start = 0
        for plant in plants:
            first = start
            for s, seg in enumerate(segments):
                mine = start
                for i, run in enumerate(seg.runs):
                    if run.plant is plant:
                        b = np.atleast_2d(run.r).shape[0]
                        self.rows[s, i] = slice(start, start + b)
                        order[s] += range(start, start + b)
                        start += b
                if plant.is_linear and start > mine:
                    self.blocks.append((plant, slice(mine, start)))
            if not plant.is_linear:
                self.blocks.append((plant, slice(first, start)))
        self.size = start
        self.segment_rows = [np.asarray(o, dtype=np.int64) for o in order]
        for (s, i), rows in self.rows.items():
            at = int(np.searchsorted(self.segment_rows[s], rows.start))
            self.local[s, i] = slice(at, at + rows.stop - rows.start)

    def controller_groups(self, s: int, runs: Sequence[Run]) -> tuple[list[Plant], list[int]]:
        """The distinct plants of segment ``s`` (global order) and each one's row count."""
        counts = {id(p): 0 for p in self.plants}
        for i, run in enumerate(runs):
            rows = self.rows[s, i]
            counts[id(run.plant)] += rows.stop - rows.start
        plants = [p for p in self.plants if counts[id(p)]]
        return plants, [counts[id(p)] for p in plants]


class _Loop:
    """The state of every row while the loop advances."""

    def __init__(self, segments: Sequence[Segment]) -> None:
        self.segments, self.layout = segments, _Layout(segments)
        runs = {key: segments[key[0]].runs[key[1]] for key in self.layout.rows}
        if len({run.plant.dt for run in runs.values()}) > 1:
            raise ValueError("simulate_stacked needs runs of one sample time")
        self.dt = next(iter(runs.values())).plant.dt
        self.refs = {
            key: np.atleast_2d(np.asarray(run.r, dtype=float)) for key, run in runs.items()
        }
        self.length = {key: r.shape[1] for key, r in self.refs.items()}
        self.steps = max(self.length.values())
        self.ends: dict[int, list[tuple[int, int]]] = {}
        for key in sorted(self.length):
            self.ends.setdefault(self.length[key], []).append(key)
        B = self.layout.size
        self.r, self.x = np.zeros((B, self.steps)), np.zeros((B, MAX_ORDER))
        perts = []
        for key, run in runs.items():  # references held at their last value, initial states
            rows, r, n = self.layout.rows[key], self.refs[key], run.plant.order
            self.r[rows, : r.shape[1]] = r
            self.r[rows, r.shape[1] :] = r[:, -1:]
            perts.append((rows, run.perturbation, n, r.shape[1]))
            if run.x0 is not None:
                x0 = np.asarray(run.x0, dtype=float)
                if x0.shape != (len(r), n):
                    raise ValueError(
                        f"x0 has shape {x0.shape}; plant '{run.plant.name}' needs ({len(r)}, {n})"
                    )
                self.x[rows, :n] = x0
        self.act = RowPerturbations(perts, self.steps, self.dt)
        self.xs = np.empty((self.steps + 1, B, MAX_ORDER))
        self.xs[0] = self.x
        self.u = np.empty((self.steps, B))
        self.diverged = np.zeros(B, dtype=bool)
        self.ended = np.zeros(B, dtype=bool)
        self.final: dict[tuple[int, int], np.ndarray] = {}
        self.advance = [(plant_stepper(p), p.order, rows) for p, rows in self.layout.blocks]

    def end(self, k: int) -> list[tuple[int, int]]:
        """Close the runs of length ``k``: their divergence as it stood, their rows dropped."""
        done = self.ends.get(k, [])
        for key in done:
            rows = self.layout.rows[key]
            self.final[key] = self.diverged[rows].copy()
            self.ended[rows] = True
        for s, seg in enumerate(self.segments):
            finish = getattr(seg.controller, "finish", None)
            mine = [self.layout.local[key] for key in done if key[0] == s]
            if finish is not None and mine:
                finish(np.concatenate([np.arange(sl.start, sl.stop) for sl in mine]))
        return done

    def control(self, k: int) -> np.ndarray:
        """Every controller's controls at sample ``k`` (NaN for the runs that ended)."""
        xm, rk = self.act.measure(self.x, k), self.r[:, k]
        u = np.empty(self.layout.size)
        for seg, rows in zip(self.segments, self.layout.segment_rows, strict=True):
            if rows.size:
                u[rows] = np.asarray(seg.controller.step(xm[rows], rk[rows]), dtype=float)
        u[self.ended] = np.nan
        return u

    def step(self, k: int) -> None:
        """Sample ``k``: every controller, the actuators, every plant, the divergence test."""
        u = self.control(k)
        u = self.act.actuate(u)
        self.u[k] = u
        ua = self.act.applied(u, k)
        nxt = np.zeros_like(self.x)
        for advance, n, rows in self.advance:
            nxt[rows, :n] = advance(self.x[rows, :n], ua[rows])
        bad = ~np.all(np.isfinite(nxt) & (np.abs(nxt) < DIVERGENCE_BOUND), axis=1)
        self.diverged |= bad
        self.x = np.where(self.diverged[:, None], self.x, nxt)
        self.xs[k + 1] = self.x

    def result(self, s: int, i: int) -> Trajectory:
        """Run ``i`` of segment ``s`` as a :class:`Trajectory`."""
        run, rows, n = self.segments[s].runs[i], self.layout.rows[s, i], self.length[s, i]
        order = run.plant.order
        x = np.ascontiguousarray(self.xs[: n + 1, rows, :order].transpose(1, 0, 2))
        b = x.shape[0]
        y = run.plant.output(x.reshape(-1, order)).reshape(b, n + 1)
        u = np.ascontiguousarray(self.u[:n, rows].T)
        t = np.arange(n + 1) * run.plant.dt
        return Trajectory(t=t, x=x, u=u, r=self.refs[s, i], y=y, diverged=self.final[s, i])


def controller_rows(segments: Sequence[Segment]) -> list[list[slice]]:
    """Per segment, per run: the run's rows in the batch its controller is reset with."""
    local = _Layout(segments).local
    return [[local[s, i] for i in range(len(seg.runs))] for s, seg in enumerate(segments)]


def simulate_stacked(
    segments: Sequence[Segment],
    on_end: Callable[[int, list[tuple[int, int]]], None] | None = None,
) -> list[list[Trajectory]]:
    """Simulate every segment's runs (one sample time, any lengths) in one loop.

    ``on_end(k, [(segment, run), ...])`` is called after the runs of length ``k`` ended.
    Returns per segment, per run, its :class:`Trajectory`: the numbers of a loop of its own
    (to the last bit where its plant has as many rows in its segment).
    """
    if not any(seg.runs for seg in segments):
        return [[] for _ in segments]
    loop = _Loop(segments)
    for s, seg in enumerate(segments):
        if seg.runs:  # a segment without runs is never stepped
            seg.controller.reset(*loop.layout.controller_groups(s, seg.runs))
    for k in range(loop.steps + 1):
        done = loop.end(k)
        if done and on_end is not None:
            on_end(k, done)
        if k < loop.steps:
            with np.errstate(all="ignore"):
                loop.step(k)
    return [[loop.result(s, i) for i in range(len(seg.runs))] for s, seg in enumerate(segments)]


def simulate_many(runs: Sequence[Run], controller: BatchController) -> list[Trajectory]:
    """Simulate runs on several plants in lockstep, one controller call per sample.

    All runs must share the sample time and the number of samples, each its own plant
    object. Rows are stacked in the order of ``runs``; states reach the controller
    zero-padded to ``MAX_ORDER``.
    """
    lengths = {np.atleast_2d(run.r).shape[1] for run in runs}
    if len(lengths) > 1 or len({run.plant.dt for run in runs}) > 1:
        raise ValueError("simulate_many needs runs of equal length and sample time")
    if len({id(run.plant) for run in runs}) < len(runs):
        raise ValueError("simulate_many needs each run on a plant object of its own")
    (out,) = simulate_stacked([Segment(controller, runs)])
    return out


def simulate(
    plant: Plant,
    controller: Controller,
    r: np.ndarray,
    x0: np.ndarray | None = None,
    perturbation: Perturbation | None = None,
) -> Trajectory:
    """Simulate ``controller`` on ``plant`` for references ``r`` (batch, N) from ``x0`` or rest."""
    run = Run(plant, r, x0, perturbation)
    return simulate_many([run], PerPlantController(lambda _: controller))[0]
