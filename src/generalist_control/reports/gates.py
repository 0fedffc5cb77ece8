"""Gate weights of a trained policy at work: per plant, mean over closed-loop unit steps."""

from __future__ import annotations

import tempfile
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.data.windows import build_windows, integral_of_error
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import POLICY_FILE, Policy, load_policy
from generalist_control.plants.catalog import available_plants, load_plant
from generalist_control.plants.definition import Plant, pad_states
from generalist_control.simulation.scenarios import references
from generalist_control.simulation.simulate import Run, Trajectory, simulate_many

__all__ = ["gate_weights", "policy_of_run"]

POLICY_ARTIFACT = f"policy/{POLICY_FILE}"


def policy_of_run(run_id: str, client: Any) -> tuple[Policy, dict[str, Any]]:
    """Download a run's ``policy/policy.ckpt`` artifact and load it (``weights_only``)."""
    with tempfile.TemporaryDirectory(prefix="gc-policy-") as tmp:
        path = client.download_artifacts(run_id, POLICY_ARTIFACT, tmp)
        return load_policy(path)


def _mean_gates(policy: Policy, tr: Trajectory, p: Plant, tag: int, history: int) -> np.ndarray:
    """Mean gate weights the policy gave the windows it saw along closed-loop runs ``tr``."""
    B, steps = tr.r.shape
    z = integral_of_error(tr.r, tr.y[:, :steps], p.dt) if "integral" in policy.channels else None
    controls = "previous_control" in policy.channels
    x = pad_states(tr.x[:, :steps])
    tags, orders = np.full(B, tag), np.full(B, p.order)
    windows = build_windows(x, tr.r, tr.u, tags, orders, history, 1, z, controls)
    _, gates = policy.predict_windows(windows)
    return gates.mean(axis=0)


def gate_weights(
    policy: Policy,
    meta: Mapping[str, Any],
    plants: Iterable[str] | None = None,
    duration: float = 15.0,
) -> pd.DataFrame:
    """Mean gate weight per plant (rows) and expert (``expert_1 ..``) over closed-loop steps.

    The runtime's inputs along each run are rebuilt by the window builder and the gates the
    policy gives them averaged: the weights of the policy at work, not on the demonstrations.
    ``plants``: default, the catalogue's plants the policy was trained on, in tag order.
    """
    tags = {str(k): int(v) for k, v in meta["tags"].items()}
    if plants is None:
        known = set(available_plants())
        plants = [k for k in sorted(tags, key=tags.__getitem__) if k in known]
    plants = list(plants)
    missing = [p for p in plants if p not in tags]
    if missing:
        raise KeyError(f"the policy was not trained on {', '.join(missing)}")
    loaded = [load_plant(name) for name in plants]
    runtime = PolicyRuntime(policy, dict(meta))
    history = int(meta["history"])
    experts = policy.net.n_experts
    spec = {"kind": "step", "amplitude": 1.0, "duration": float(duration)}
    out: dict[str, np.ndarray] = {}
    by_dt: dict[float, list[Any]] = {}
    for p in loaded:
        by_dt.setdefault(p.dt, []).append(p)
    for group in by_dt.values():
        runs = [Run(p, *references("step", spec, p), None) for p in group]
        trajs = simulate_many(runs, RuntimeAdapter(runtime))
        for p, tr in zip(group, trajs, strict=True):
            out[p.name] = _mean_gates(policy, tr, p, tags[p.name], history)
    cols = [f"expert_{i + 1}" for i in range(experts)]
    df = pd.DataFrame([out[p] for p in plants], index=pd.Index(plants, name="plant"), columns=cols)
    return df.astype(float)
