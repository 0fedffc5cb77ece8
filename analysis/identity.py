"""What a tag-free policy's identity head makes of the plant (``model.plant: inferred``).

An inferred plant's identity head reads the plant from the window (a softmax over the
training plants that weighs the embedding rows the law sees). Two views of it:

* :func:`identity_table`: along each plant's own LQI unit step from rest (the expert's
  closed loop, as in :mod:`~analysis.separation`), at a few times:
  does the history name the plant, and how soon?
* :func:`identity_trace`: along the policy's own closed loop on the unit step, from the
  start or after its expert made the first ``N`` samples' controls
  (:class:`~analysis.handover.Handover`): does the policy keep
  naming the plant once its own controls shape the window?
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd
import torch

from analysis.handover import Handover
from analysis.separation import step_windows
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.definition import Plant
from generalist_control.simulation.scenarios import references
from generalist_control.simulation.simulate import Run, simulate_many

__all__ = ["identity_summary", "identity_table", "identity_trace"]


def _probabilities(
    policy: Policy, plants: Sequence[Plant], windows: Sequence[np.ndarray]
) -> np.ndarray:
    """The head's softmax over ``plants`` (B, P) for raw windows ``(state, mask, ref, tag)``."""
    args = [torch.as_tensor(np.asarray(a)) for a in windows]
    with torch.no_grad():
        reading = policy.output(*args).plant
    if reading is None or reading.logits is None:
        raise ValueError("the policy's plant part has no identity head (a tag or a card)")
    logits = reading.logits
    return torch.softmax(logits[:, [p.tag for p in plants]], dim=1).double().numpy()


def _row(p: Plant, plants: Sequence[Plant], prob: np.ndarray, **where: Any) -> dict[str, Any]:
    best = int(np.argmax(prob))
    index = [q.tag for q in plants].index(p.tag)
    return {
        "system": p.name,
        **where,
        "p_true": float(prob[index]),
        "guess": plants[best].name,
        "p_guess": float(prob[best]),
    }


def identity_table(
    policy: Policy,
    plants: Sequence[Plant],
    times: Sequence[float] = (0.1, 0.25, 0.5, 1.0, 2.0),
) -> pd.DataFrame:
    """How soon the identity head names the plant along its expert's unit step.

    At each time of ``times``, the window the window builder cuts from the plant's own LQI
    unit step from rest ends there; the head's softmax over ``plants`` gives ``p_true``
    (the plant itself), ``guess`` (its most probable plant) and ``p_guess``.

    Raises
    ------
    ValueError
        If the policy has no identity head, or a time is under one sample.
    """
    dt = plants[0].dt
    samples = [int(round(t / dt)) for t in times]
    if not samples or min(samples) < 1:
        raise ValueError(f"identity times must be at least one sample ({dt} s), got {times}")
    windows = step_windows(policy, plants, (max(samples) + 1) * dt)
    rows = []
    for p, w in zip(plants, windows, strict=True):
        cut = [np.asarray(a)[samples] for a in (w.state, w.mask, w.ref, w.tag)]
        prob = _probabilities(policy, plants, cut)
        rows += [_row(p, plants, q, time=k * dt) for k, q in zip(samples, prob, strict=True)]
    return pd.DataFrame(rows)


class _Traced(Handover):
    """A hand-over run that reads the identity head on the runtime's window at every sample."""

    def __init__(self, runtime: PolicyRuntime, after: int, plants: Sequence[Plant]) -> None:
        super().__init__(runtime, after)
        self.plants = plants
        self.probs: list[np.ndarray | None] = []  # per sample (runs, plants); None: refused

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        u = super().step(x, r)
        window = self.runtime.window()
        whole = len(window[3]) == x.shape[0]  # a refused run leaves the window: rows misalign
        self.probs.append(
            _probabilities(self.runtime.policy, self.plants, window) if whole else None
        )
        return u


def identity_trace(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    spec: Mapping[str, Any],
    samples: Sequence[int] = (0, 40),
) -> pd.DataFrame:
    """The identity head along the policy's own unit step, per sample.

    Parameters
    ----------
    runtime : PolicyRuntime
        The policy as the evaluation runs it (tag withheld).
    plants : sequence of Plant
    spec : mapping
        The step scenario (one run per plant).
    samples : sequence of int
        Hand-over samples ``N``: the plant's LQI controls the first ``N`` samples.

    Returns
    -------
    DataFrame
        ``system, handover_samples, sample, time, p_true, guess, p_guess``, one row per plant and
        sample until the run ends (or the runtime refuses a run, which ends every row's
        trace: the window's rows would no longer match the plants).
    """
    runs = [Run(p, *references("step", spec, p)) for p in plants]
    if any(run.r.shape[0] != 1 for run in runs):
        raise ValueError("identity_trace takes one run per plant (a step scenario)")
    rows = []
    for n in samples:
        traced = _Traced(runtime, int(n), plants)
        simulate_many(runs, traced)
        for k, prob in enumerate(traced.probs):
            if prob is None:
                break
            where = {"handover_samples": int(n), "sample": k, "time": k * plants[0].dt}
            rows += [_row(p, plants, q, **where) for p, q in zip(plants, prob, strict=True)]
    return pd.DataFrame(rows)


def identity_summary(
    table: pd.DataFrame, trace: pd.DataFrame | None = None
) -> dict[str, dict[str, Any]]:
    """Per time of :func:`identity_table`: plants named, median ``p_true``, the misnamed.

    With a :func:`identity_trace`, also per hand-over sample and plant the share of the
    policy's own samples (from the hand-over on) on which the head names the plant.
    """
    out: dict[str, dict[str, Any]] = {}
    for t, g in table.groupby("time"):
        out[f"{t:g}"] = {
            "plants": len(g),
            "named": int((g.guess == g.system).sum()),
            "median_p_true": float(g.p_true.median()),
            "misnamed": {s: q for s, q in zip(g.system, g.guess, strict=True) if s != q},
        }
    if trace is not None:
        own = trace[trace["sample"] >= trace.handover_samples]
        for n, g in own.groupby("handover_samples"):
            named = (g.guess == g.system).groupby(g.system).mean()
            out[f"own_from_{n}"] = {s: float(v) for s, v in named.items()}
    return out
