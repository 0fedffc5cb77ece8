"""Why a policy without its tag can miss a plant: how soon the history tells plants apart.

Without the tag, the policy's only clue to the plant is its window (history of the
normalised, window-scaled state, integral, previous control where the policy has it, and
reference; the mask gives the order). For a unit step from rest every plant's window starts
alike: the state at rest, the reference at one, the error integral ramping at the same rate
and the first previous control zero, so the first controls must be guessed. In this replay
the previous-control channel holds the expert's own controls.
This module measures, on the LQI experts' own unit-step responses and through the policy's
own preprocessing (:meth:`~generalist_control.model.policy.Policy.network_inputs`):

* ``input_gap[k]``: for plant ``p`` and another plant ``q``, the relative distance of the
  windows the network sees at sample ``k``, ``|v_p - v_q| / max(|v_p|, |v_q|)`` (mask
  included, so plants of different order are apart at once);
* ``control_gap[k]``: the relative distance of the experts' answers in the units the policy
  learns them (normalised, divided by the window scale);
* ``separation_time``: the first time at which ``p``'s window is more than ``threshold`` away
  from every other plant's; before it ``p`` is confusable with its nearest plant.

A plant whose windows stay within the threshold of another plant's while the experts'
controls differ by far more cannot be told apart by the history early enough: the policy
must answer both with one control.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
import torch

from generalist_control.data.windows import Windows, build_windows, integral_of_error
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import Plant, pad_states
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import PerPlantController, Run, simulate_many

__all__ = ["network_views", "separation_table", "step_windows"]


def network_views(
    policy: Policy, plants: Sequence[Plant], duration: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """What the network sees and what it must answer, per plant and sample of a unit step.

    Parameters
    ----------
    policy : Policy
        Its normaliser and window scaling are applied; its tags are not used.
    plants : sequence of Plant
        All with the same ``dt``; unit steps (times ``amplitude_scale``) from rest.
    duration : float
        Seconds of the response.

    Returns
    -------
    inputs : ndarray, shape (P, N, F)
        The flattened network input (state, mask, reference) of each window.
    controls : ndarray, shape (P, N)
        The expert's first control of each window in the policy's learned units.
    """
    inputs, controls = [], []
    for w in step_windows(policy, plants, duration):
        args = [torch.tensor(a) for a in (w.state, w.mask, w.ref, w.tag)]
        with torch.no_grad():
            x, m, r, tag, s = policy.network_inputs(*args)
            u = policy.normaliser.normalise_controls(torch.tensor(w.target), tag) / s
        inputs.append(torch.cat([x.flatten(1), m.flatten(1), r], dim=1).numpy())
        controls.append(u[:, 0].numpy())
    return np.stack(inputs), np.stack(controls)


def step_windows(policy: Policy, plants: Sequence[Plant], duration: float) -> list[Windows]:
    """Each plant's LQI unit step from rest, as the policy's window builder cuts it."""
    steps = int(round(duration / plants[0].dt))
    runs = [Run(p, np.full((1, steps), p.amplitude_scale)) for p in plants]
    trajs = simulate_many(runs, PerPlantController(LQIController))
    out = []
    for p, tr in zip(plants, trajs, strict=True):
        integral = "integral" in policy.channels
        z = integral_of_error(tr.r, tr.y[:, :steps], p.dt) if integral else None
        out.append(
            build_windows(
                pad_states(tr.x[:, :steps]),
                tr.r,
                tr.u,
                np.array([p.tag]),
                np.array([p.order]),
                policy.history,
                1,
                z,
                "previous_control" in policy.channels,
            )
        )
    return out


def _gaps(inputs: np.ndarray, controls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairwise relative input and control gaps, shape (P, P, N); the diagonal is inf."""
    diff = np.linalg.norm(inputs[:, None] - inputs[None], axis=-1)
    size = np.linalg.norm(inputs, axis=-1)
    scale = np.maximum(size[:, None], size[None]).clip(min=1e-12)
    input_gap = diff / scale
    c = np.abs(controls)
    control_gap = np.abs(controls[:, None] - controls[None]) / np.maximum(
        c[:, None], c[None]
    ).clip(min=1e-12)
    eye = np.eye(len(inputs), dtype=bool)
    input_gap[eye] = np.inf
    return input_gap, control_gap


def separation_table(
    policy: Policy,
    plants: Sequence[Plant],
    duration: float = 2.0,
    threshold: float = 0.1,
    views: tuple[np.ndarray, np.ndarray] | None = None,
) -> pd.DataFrame:
    """Per plant: its nearest plant in the network's eyes and when the history separates them.

    Returns
    -------
    DataFrame
        ``system, order, nearest, separation_time, input_gap, control_gap``: the plant most
        alike at the first sample where the expert acts (``nearest``), the first time
        ``p``'s window lies more than ``threshold`` from every other plant's
        (``separation_time``, ``inf`` if never within ``duration``), and, over the samples
        before it (at least the first), the median input gap to ``nearest`` and the median
        gap between the two experts' controls. ``views``: :func:`network_views`' result for
        these plants and ``duration``, if already computed.
    """
    inputs, controls = views if views is not None else network_views(policy, plants, duration)
    input_gap, control_gap = _gaps(inputs, controls)
    dt = plants[0].dt
    start = 1  # sample 0 is at rest for every plant; the expert acts from sample 1
    rows = []
    for i, p in enumerate(plants):
        closest = input_gap[i].min(axis=0)  # (N,)
        apart = np.nonzero(closest[start:] > threshold)[0]
        first = start + int(apart[0]) if apart.size else inputs.shape[1]
        j = int(np.argmin(input_gap[i, :, start]))
        span = slice(start, max(first, start + 1))
        rows.append(
            {
                "system": p.name,
                "order": p.order,
                "nearest": plants[j].name,
                "separation_time": first * dt if apart.size else float("inf"),
                "input_gap": float(np.median(input_gap[i, j, span])),
                "control_gap": float(np.median(control_gap[i, j, span])),
            }
        )
    return pd.DataFrame(rows)
