"""Many batches of runs, on many plants and under several controllers, in one sampled loop.

Each row gets :func:`~generalist_control.simulation.simulate.simulate_many`'s arithmetic, so
a run's trajectory is the one it gives (bit for bit, tests/test_stacked.py).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.simulate import (
    DIVERGENCE_BOUND,
    BatchController,
    Run,
    Trajectory,
    plant_stepper,
)

__all__ = ["Segment", "controller_rows", "simulate_stacked"]


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


class _Actuators:
    """The perturbations of every row, applied the way ``Perturbation`` applies them."""

    def __init__(self, runs: Sequence[tuple[slice, Run]], steps: int, dt: float) -> None:
        rate, clip, gain, dist, noise = [], [], [], [], []
        for rows, run in runs:
            p, idx = run.perturbation, np.arange(rows.start, rows.stop)
            if p is None:
                continue
            if p.rate_limit is not None:
                rate.append((idx, p.rate_limit * dt))
            if p.u_limit is not None:
                clip.append((idx, p.u_limit))
            if p.actuator_gain != 1.0:
                gain.append((idx, p.actuator_gain))
            if p.disturbance:
                dist.append((idx, p.disturbance, _first(p.disturbance_start, dt, steps)))
            if p.noise_std is not None:
                noise.append((rows, run, _first(p.noise_start, dt, steps)))
        self.rate, self.clip, self.gain = _stack(rate), _stack(clip), _stack(gain)
        self.dist = [(i, np.full(i.size, v), k0) for i, v, k0 in dist]
        self.noise = [_noise(rows, run, k0) for rows, run, k0 in noise]
        self.prev = np.zeros(max((r.stop for r, _ in runs), default=0))

    def measure(self, x: np.ndarray, k: int) -> np.ndarray:
        """The states the controllers see at sample ``k``: ``x`` plus any noise due."""
        due = [(rows, z[k - k0]) for rows, z, k0 in self.noise if k0 <= k < k0 + len(z)]
        if not due:
            return x
        xm = x.copy()
        for rows, z in due:
            n = z.shape[1]
            xm[rows, :n] = x[rows, :n] + z
        return xm

    def actuate(self, u: np.ndarray) -> np.ndarray:
        """Rate limit, then amplitude limit (in place); the rate limit remembers the result."""
        if self.rate is not None:
            idx, du = self.rate
            prev = self.prev[idx]
            u[idx] = np.clip(u[idx], prev - du, prev + du)
        if self.clip is not None:
            idx, lim = self.clip
            u[idx] = np.clip(u[idx], -lim, lim)
        if self.rate is not None:
            self.prev[self.rate[0]] = u[self.rate[0]]
        return u

    def applied(self, u: np.ndarray, k: int) -> np.ndarray:
        """What the plants receive: the delivered ``u`` times any gain, plus any disturbance."""
        due = [(i, v) for i, v, k0 in self.dist if k >= k0]
        if self.gain is None and not due:
            return u
        ua = u.copy()
        if self.gain is not None:
            idx, g = self.gain
            ua[idx] = u[idx] * g
        for idx, v in due:
            ua[idx] = ua[idx] + v
        return ua


def _first(start: float, dt: float, steps: int) -> int:
    """The first sample ``k`` with ``k * dt >= start`` (as the simulator tests it)."""
    return next((k for k in range(steps) if k * dt >= start), steps)


def _stack(parts: list[tuple[np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray] | None:
    if not parts:
        return None
    idx = np.concatenate([i for i, _ in parts])
    return idx, np.concatenate([np.full(i.size, v) for i, v in parts])


def _noise(rows: slice, run: Run, k0: int) -> tuple[slice, np.ndarray, int]:
    """The run's noise from sample ``k0`` on: one draw, the numbers of one draw per sample."""
    pert, plant = run.perturbation, run.plant
    assert pert is not None and pert.noise_std is not None
    b, steps = np.atleast_2d(run.r).shape
    rng = np.random.default_rng(pert.seed)
    return rows, pert.noise(rng.normal(size=(max(steps - k0, 0), b, plant.order))), k0


def _initial(layout: _Layout, segments: Sequence[Segment]) -> np.ndarray:
    """Every row's initial state, zero-padded."""
    x = np.zeros((layout.size, MAX_ORDER))
    for (s, i), rows in layout.rows.items():
        run = segments[s].runs[i]
        n = run.plant.order
        if run.x0 is not None:
            x0 = np.asarray(run.x0, dtype=float)
            if x0.shape != (rows.stop - rows.start, n):
                raise ValueError(
                    f"x0 has shape {x0.shape}; plant '{run.plant.name}' needs "
                    f"({rows.stop - rows.start}, {n})"
                )
            x[rows, :n] = x0
    return x


class _Loop:
    """The state of every row while the loop advances."""

    def __init__(self, segments: Sequence[Segment]) -> None:
        self.segments, self.layout = segments, _Layout(segments)
        runs = [(rows, segments[s].runs[i]) for (s, i), rows in self.layout.rows.items()]
        if len({run.plant.dt for _, run in runs}) > 1:
            raise ValueError("simulate_stacked needs runs of one sample time")
        self.dt = runs[0][1].plant.dt
        self.length = {key: np.atleast_2d(segments[key[0]].runs[key[1]].r).shape[1]
                       for key in self.layout.rows}  # fmt: skip
        self.steps = max(self.length.values())
        self.ends: dict[int, list[tuple[int, int]]] = {}
        for key in sorted(self.length):
            self.ends.setdefault(self.length[key], []).append(key)
        B = self.layout.size
        self.r = np.zeros((B, self.steps))
        for (s, i), rows in self.layout.rows.items():
            r = np.atleast_2d(np.asarray(segments[s].runs[i].r, dtype=float))
            self.r[rows, : r.shape[1]] = r
            self.r[rows, r.shape[1] :] = r[:, -1:]
        self.act = _Actuators(runs, self.steps, self.dt)
        self.x = _initial(self.layout, segments)
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
        r = np.atleast_2d(np.asarray(run.r, dtype=float))
        u = np.ascontiguousarray(self.u[:n, rows].T)
        t = np.arange(n + 1) * run.plant.dt
        return Trajectory(t=t, x=x, u=u, r=r, y=y, diverged=self.final[s, i])


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
    Returns per segment, per run, what ``simulate_many`` returns.
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
