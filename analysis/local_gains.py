"""The policy's local feedback gains on its plant's own closed loop, beside LQI's.

A policy that imitates LQI well answers a small change of the newest state ``x_k`` (and
error integral ``z_k``) as the expert's law does, ``du = -Kx dx - Ki dz``, whether it
learned the law in position form or in velocity form (``u_k = u_(k-1) - Kx (x_k -
x_(k-1)) - ...``): either way the derivative of its control with respect to the newest
sample is ``-Kx`` (``-Ki``). :func:`local_gains` measures that derivative where the policy
would take over from the expert (:mod:`~analysis.handover`): after
``samples`` samples of the plant's LQI on a unit step from rest, by automatic
differentiation of the network on the window its runtime holds, and sets it beside LQI's
gains, in physical units and in the policy's normalised units (gain times the state's
scale over the control's), where plants of very different physics become comparable.
With the previous control as a channel (the ``previous_control`` channel) its derivative is
listed too (in physical units 1 for the velocity form, 0 for the position form).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd
import torch

from analysis.handover import Handover
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.plants.definition import MAX_ORDER, Plant
from generalist_control.simulation.lqi import design_lqi
from generalist_control.simulation.scenarios import references
from generalist_control.simulation.simulate import Run, simulate_many

__all__ = ["gain_summary", "local_gains"]


def _jacobian(runtime: PolicyRuntime) -> np.ndarray:
    """D u_k / d (newest window sample), (B, channels), for the runtime's current windows."""
    state, mask, ref, tag = (torch.as_tensor(np.array(a)) for a in runtime.window())
    state.requires_grad_(True)
    u, _ = runtime.policy(state, mask, ref, tag)
    u[:, 0].sum().backward()  # rows are independent: each row's gradient is its own
    assert state.grad is not None
    return state.grad[:, -1].double().numpy()


def local_gains(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    spec: Mapping[str, Any],
    samples: int = 40,
) -> pd.DataFrame:
    """The policy's and LQI's gains after ``samples`` samples of LQI on the step ``spec``.

    Returns
    -------
    DataFrame
        One row per plant and input (``x1`` .. ``xn``, ``z`` for an integrating policy,
        ``u_prev`` with the previous control as a channel): ``lqi`` (``-Kx``, ``-Ki``, 0)
        and ``policy`` (the derivative of its control) in physical units, ``lqi_norm`` and
        ``policy_norm`` in the policy's normalised units, and ``ratio`` = policy / LQI.
    """
    steps = int(samples) + 1  # the runtime is stepped at sample `samples`: its window there
    runs = []
    for p in plants:
        r, x0 = references("step", spec, p)
        if r.shape[1] < steps:
            raise ValueError(
                f"the step scenario lasts {r.shape[1]} samples; local gains after {samples} "
                f"need at least {steps}: lengthen its duration or lower evaluation.gain_samples"
            )
        runs.append(Run(p, r[:, :steps], x0))
    simulate_many(runs, Handover(runtime, steps))
    if len(runtime.window()[3]) != sum(run.r.shape[0] for run in runs):  # rows stay aligned
        raise RuntimeError(
            "the policy's runtime refused a run on LQI's own closed loop (its output left "
            "its range), so its rows no longer match the plants: no local gains"
        )
    jac = _jacobian(runtime)  # rows: one per run, plants in order (one run each for a step)
    rows: list[dict[str, Any]] = []
    row = 0
    for p, run in zip(plants, runs, strict=True):
        rows.extend(_plant_rows(runtime, p, jac[row]))
        row += run.r.shape[0]
    return pd.DataFrame(rows)


def _plant_rows(runtime: PolicyRuntime, p: Plant, jac: np.ndarray) -> list[dict[str, Any]]:
    """One plant's rows of :func:`local_gains` from its row ``jac`` of the Jacobian."""
    g = design_lqi(p)
    norm = runtime.policy.normaliser
    sx = norm.state_scale[p.tag].double().cpu().numpy()
    su = float(norm.control_scale[p.tag])
    inputs = [(f"x{i + 1}", i, -float(g.Kx[i])) for i in range(p.order)]
    if runtime.integral:
        inputs.append(("z", MAX_ORDER, -float(g.Ki)))
    if runtime.controls:
        inputs.append(("u_prev", jac.shape[0] - 1, 0.0))
    rows = []
    for name, j, lqi in inputs:
        scale = sx[j] / su  # what the network sees per unit of what it answers
        policy = float(jac[j])
        rows.append(
            {
                "system": p.name,
                "input": name,
                "lqi": lqi,
                "policy": policy,
                "lqi_norm": lqi * scale,
                "policy_norm": policy * scale,
                "ratio": policy / lqi if lqi != 0.0 else np.nan,
            }
        )
    return rows


def gain_summary(gains: pd.DataFrame) -> dict[str, dict[str, Any]]:
    """Per plant: how far the policy's local gains on the state ``x`` are from LQI's.

    ``norm_ratio``: the norm of the policy's normalised state gains over LQI's; ``largest``:
    the state where LQI's normalised gain is largest, and ``same_sign`` whether the policy's
    gain there has LQI's sign. The error integral and the previous control are left out: a
    law in velocity form answers the integral through the previous control, so its
    derivative with respect to ``z`` is 0 where LQI's is ``-Ki``.
    """
    out = {}
    states = gains[gains.input.str.fullmatch(r"x\d+")]
    for system, part in states.groupby("system", sort=True):
        big = part.iloc[int(np.argmax(np.abs(part.lqi_norm.to_numpy())))]
        out[str(system)] = {
            "norm_ratio": float(np.linalg.norm(part.policy_norm) / np.linalg.norm(part.lqi_norm)),
            "largest": str(big.input),
            "same_sign": bool(np.sign(big.policy_norm) == np.sign(big.lqi_norm)),
        }
    return out
