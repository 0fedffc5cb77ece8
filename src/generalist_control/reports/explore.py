"""Tables and figures for exploring the plants and the dataset (``notebooks/01_*``).

The notebook only calls these, so what it shows is computed by tested code; figures are
drawn on the Agg canvas (no pyplot state).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import control
import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from generalist_control.data.demos import DemoSet
from generalist_control.plants.catalog import available_plants, load_plant
from generalist_control.plants.definition import Plant
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.scenarios import references
from generalist_control.simulation.simulate import simulate

__all__ = [
    "lqi_step_responses",
    "manifest_table",
    "plant_class",
    "plant_properties",
    "plant_table",
    "plot_step_responses",
    "plot_windows",
]

_TOL = 1e-9


def plant_properties(plant: Plant) -> dict[str, Any]:
    """Open-loop ``poles``, ``zeros``, ``stability``, ``min_phase`` of a plant's (linear) model.

    ``stability`` is ``stable``, ``marginal`` (poles on the imaginary axis, none right of it)
    or ``unstable``; ``min_phase``: every transmission zero in the open left half plane.
    """
    poles = np.linalg.eigvals(plant.A)
    zeros = np.asarray(control.ss(plant.A, plant.B, plant.C, 0).zeros())
    if np.all(poles.real < -_TOL):
        stability = "stable"
    elif np.all(poles.real < _TOL):
        stability = "marginal"
    else:
        stability = "unstable"
    return {
        "poles": poles,
        "zeros": zeros,
        "stability": stability,
        "min_phase": bool(np.all(zeros.real < -_TOL)),
    }


def plant_class(plant: Plant) -> dict[str, Any]:
    """What makes a plant hard: instability, non-minimum phase, order, the least damping."""
    props = plant_properties(plant)
    poles, zeros = props["poles"], props["zeros"]
    complex_poles = poles[np.abs(poles.imag) > _TOL]
    damping = -complex_poles.real / np.abs(complex_poles)
    return {
        "order": plant.order,
        "nonlinear": not plant.is_linear,
        "open_loop_unstable": bool(np.any(poles.real > _TOL)),
        "non_minimum_phase": bool(np.any(zeros.real > _TOL)),
        "min_damping": float(damping.min()) if damping.size else None,
    }


def plant_table(names: Iterable[str] | None = None) -> pd.DataFrame:
    """The catalogue (default: every plant in ``conf/plants``), one row per plant by tag."""
    plants = sorted((load_plant(n) for n in (names or available_plants())), key=lambda p: p.tag)
    rows = []
    for p in plants:
        props = plant_properties(p)
        rows.append(
            {
                "plant": p.name,
                "tag": p.tag,
                "order": p.order,
                "linear": p.is_linear,
                "stability": props["stability"],
                "min_phase": props["min_phase"],
                "poles": np.array2string(np.round(props["poles"], 3), separator=", "),
                "zeros": np.array2string(np.round(props["zeros"], 3), separator=", "),
                "amplitude_scale": p.amplitude_scale,
                "description": p.description,
            }
        )
    return pd.DataFrame(rows).set_index("plant")


def lqi_step_responses(
    names: Sequence[str], duration: float = 10.0, amplitude: float = 1.0
) -> pd.DataFrame:
    """Closed-loop LQI responses to a step from rest, long form ``plant, t, r, y, u``."""
    spec = {"kind": "step", "amplitude": float(amplitude), "duration": float(duration)}
    frames = []
    for name in names:
        plant = load_plant(name)
        r, x0 = references("step", spec, plant)
        tr = simulate(plant, LQIController(plant), r, x0)
        n = tr.r.shape[1]
        frames.append(
            pd.DataFrame(
                {
                    "plant": name,
                    "t": tr.t,
                    "r": np.append(tr.r[0], tr.r[0, -1]),
                    "y": tr.y[0],
                    "u": np.append(tr.u[0], np.nan)[: n + 1],
                }
            )
        )
    return pd.concat(frames, ignore_index=True)


def _figure(width: float, height: float, nrows: int, ncols: int) -> tuple[Figure, np.ndarray]:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, np.atleast_2d(fig.subplots(nrows, ncols, squeeze=False))


def plot_step_responses(responses: pd.DataFrame, ncols: int = 3) -> Figure:
    """One panel per plant: output and reference (left axis), control (right axis)."""
    plants = list(dict.fromkeys(responses["plant"]))
    nrows = max(1, -(-len(plants) // ncols))
    fig, axes = _figure(4.2 * ncols, 2.6 * nrows, nrows, ncols)
    for ax, name in zip(axes.flat, plants, strict=False):
        part = responses[responses["plant"] == name]
        ax.plot(part["t"], part["r"], "k--", lw=1, label="r")
        ax.plot(part["t"], part["y"], label="y")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("t [s]")
        twin = ax.twinx()
        twin.step(part["t"], part["u"], where="post", color="C1", lw=1, label="u")
        twin.tick_params(labelsize=7, colors="C1")
        twin.set_ylabel("u", color="C1", fontsize=8)
        ax.legend(loc="lower right", fontsize=7)
    for ax in list(axes.flat)[len(plants) :]:
        ax.set_axis_off()
    return fig


def manifest_table(manifest: Mapping[str, Any]) -> pd.DataFrame:
    """Per-plant facts of a dataset manifest (``data/demos/manifest.json``), by plant."""
    df = pd.DataFrame.from_dict(dict(manifest.get("plants") or {}), orient="index")
    df.index.name = "plant"
    return df.sort_values("tag") if "tag" in df else df


def plot_windows(demos: DemoSet, history: int, horizon: int, n: int = 4, seed: int = 0) -> Figure:
    """``n`` random training windows (:meth:`DemoSet.windows`): histories and LQI targets."""
    windows = demos.windows(history, horizon)
    rng = np.random.default_rng(seed)
    picks = np.sort(rng.choice(len(windows), size=min(n, len(windows)), replace=False))
    fig, axes = _figure(4.2 * len(picks), 3.0, 1, max(1, len(picks)))
    k_hist = np.arange(-history + 1, 1)
    k_next = np.arange(horizon)
    for ax, i in zip(axes.flat, picks, strict=False):
        traj = int(windows.traj[i])
        order = int(demos.order[traj])
        for j in range(order):
            ax.plot(k_hist, windows.state[i, :, j], marker=".", lw=1, label=f"x{j + 1}")
        ax.plot(k_hist, windows.ref[i], "k--", lw=1, label="r")
        if windows.target is not None:
            ax.step(k_next, windows.target[i], where="post", color="C3", lw=2, label="u target")
        ax.axvline(0, color="grey", lw=0.5)
        ax.set_title(f"{demos.plant[traj]} (tag {int(windows.tag[i])}), window {i}", fontsize=8)
        ax.set_xlabel("sample k (0 = now)")
        ax.legend(fontsize=6)
    return fig
