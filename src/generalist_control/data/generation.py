"""The demonstrations: every plant's LQI expert on every step of the amplitude grid.

The ``generate`` stage (:mod:`generalist_control.generate`) calls :func:`generate_demos`
and :func:`build_manifest`; every input is validated before anything is simulated.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from generalist_control import __version__
from generalist_control.data.demos import FORMAT_VERSION, DemoSet, content_hash
from generalist_control.data.windows import windows_per_trajectory
from generalist_control.plants.plant import MAX_ORDER, Plant, pad_states
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.simulate import simulate

__all__ = ["DataConfigError", "amplitude_grid", "build_manifest", "generate_demos"]


class DataConfigError(ValueError):
    """The ``data`` config is invalid; the message names the field."""


def amplitude_grid(cfg: Mapping[str, Any]) -> np.ndarray:
    """The sorted step-amplitude grid described by ``data.amplitudes``.

    Each segment ``{start, stop, step}`` contributes ``start, start + step, ..., stop``;
    ``symmetric`` adds the negatives. Zero (no step) is never included.

    Raises
    ------
    DataConfigError
        If a segment is malformed or reaches outside ``+-limit``.

    Examples
    --------
    >>> amplitude_grid({"limit": 20, "symmetric": True,
    ...                 "segments": [{"start": 5, "stop": 20, "step": 5}]}).tolist()
    [-20.0, -15.0, -10.0, -5.0, 5.0, 10.0, 15.0, 20.0]
    """
    limit = float(cfg.get("limit", 20.0))
    values: list[np.ndarray] = []
    segments = cfg.get("segments") or []
    if not segments:
        raise DataConfigError("data.amplitudes.segments is empty: give at least one segment")
    for i, seg in enumerate(segments):
        field = f"data.amplitudes.segments[{i}]"
        try:
            start, stop, step = (float(seg[k]) for k in ("start", "stop", "step"))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataConfigError(f"{field} needs numeric 'start', 'stop' and 'step'") from exc
        if not step > 0:
            raise DataConfigError(f"{field}.step must be positive, got {step}")
        if stop < start:
            raise DataConfigError(f"{field}.stop ({stop}) is below its start ({start})")
        for key, v in (("start", start), ("stop", stop)):
            if abs(v) > limit:
                raise DataConfigError(
                    f"{field}.{key} = {v} lies outside the amplitude limit +-{limit} "
                    "(data.amplitudes.limit)"
                )
        count = int(np.floor((stop - start) / step + 1e-9)) + 1
        values.append(np.round(start + step * np.arange(count), 10))
    grid = np.concatenate(values)
    if cfg.get("symmetric", False):
        grid = np.concatenate([grid, -grid])
    grid = np.unique(grid[grid != 0.0])
    return grid


def _steps(data: Mapping[str, Any], plants: Sequence[Plant]) -> tuple[float, int]:
    dts = {p.dt for p in plants}
    if len(dts) != 1:
        raise DataConfigError(
            "plants of one set must share a sample time; got "
            + ", ".join(f"{p.name}: {p.dt}" for p in plants)
        )
    dt = dts.pop()
    history, horizon = int(data["history"]), int(data["horizon"])
    if history < 1 or horizon < 1:
        raise DataConfigError("data.history and data.horizon must be at least 1")
    steps = int(round(float(data["duration"]) / dt))
    if steps < horizon + 1:
        raise DataConfigError(
            f"data.duration = {data['duration']} s gives {steps} samples at dt = {dt} s; "
            f"need more than data.horizon = {horizon}"
        )
    return dt, steps


def generate_demos(
    plants: Sequence[Plant], data: Mapping[str, Any], progress: bool | None = None
) -> DemoSet:
    """Simulate every plant's LQI expert on every step of the amplitude grid.

    Parameters
    ----------
    plants : sequence of Plant
    data : mapping
        The ``data`` config (``duration``, ``history``, ``horizon``, ``amplitudes``).
    progress : bool, optional
        Show a progress bar; by default only on a terminal.
    """
    grid = amplitude_grid(data["amplitudes"])
    dt, steps = _steps(data, plants)
    controllers = [LQIController(p, design_lqi(p)) for p in plants]  # validates all first
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("x", "r", "u", "y", "amp")}
    disable = None if progress is None else not progress
    for plant, ctrl in tqdm(
        list(zip(plants, controllers, strict=True)),
        desc="generate",
        unit="plant",
        disable=disable,
        file=sys.stderr,
    ):
        amp = grid * plant.amplitude_scale
        r = np.repeat(amp[:, None], steps, axis=1)
        traj = simulate(plant, ctrl, r)
        if traj.diverged.any():
            raise RuntimeError(f"plant '{plant.name}': LQI closed loop diverged in the data stage")
        parts["x"].append(pad_states(traj.x[:, :steps]))
        parts["r"].append(traj.r)
        parts["u"].append(traj.u)
        parts["y"].append(traj.y[:, :steps])
        parts["amp"].append(amp)
    n = len(grid)
    return DemoSet(
        x=np.concatenate(parts["x"]),
        r=np.concatenate(parts["r"]),
        u=np.concatenate(parts["u"]),
        y=np.concatenate(parts["y"]),
        tag=np.repeat([p.tag for p in plants], n).astype(np.int64),
        order=np.repeat([p.order for p in plants], n).astype(np.int64),
        plant=np.repeat([p.name for p in plants], n),
        amplitude=np.concatenate(parts["amp"]),
        dt=dt,
    )


def build_manifest(
    plants: Sequence[Plant], demos: DemoSet, data: Mapping[str, Any], config: dict[str, Any]
) -> dict[str, Any]:
    """The manifest: window counts, per-plant facts, the resolved config and content hash."""
    history, horizon = int(data["history"]), int(data["horizon"])
    steps = demos.r.shape[1]
    per_traj = windows_per_trajectory(steps, horizon)
    n_traj = {p.name: int(np.sum(demos.plant == p.name)) for p in plants}
    return {
        "format_version": FORMAT_VERSION,
        "generator": f"generalist_control {__version__}",
        "n_demonstrations": per_traj * len(demos.r),
        "n_trajectories": len(demos.r),
        "steps_per_trajectory": steps,
        "windows_per_trajectory": per_traj,
        "dt": demos.dt,
        "history": history,
        "horizon": horizon,
        "max_order": MAX_ORDER,
        "plants": {
            p.name: {
                "tag": p.tag,
                "order": p.order,
                "linear": p.is_linear,
                "amplitude_scale": p.amplitude_scale,
                "n_trajectories": n_traj[p.name],
                "n_demonstrations": n_traj[p.name] * per_traj,
            }
            for p in plants
        },
        "config": config,
        "content_hash": content_hash(demos, config),
    }
