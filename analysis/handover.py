"""Hand-over from the expert: is a plant lost in the policy's first controls.

Without its tag the policy must tell the plant from the plant's response to its own first
controls (``docs/results.md``, "Without the tag"). If those first controls are what loses a
plant, the same policy should hold it once the plant's own LQI expert has made them. The
test: a unit step from rest where the expert controls the first ``N`` samples and the
policy every sample after; the policy's runtime is stepped throughout, so its window, error
integral and previous-control channel hold the expert's closed loop when it takes over
(:meth:`~generalist_control.deploy.runtime.PolicyRuntime.record_applied`). ``N = 0`` is the
evaluation's own GC run. A plant that still diverges when the expert has made the first
second of controls is lost by something other than the ambiguity of its first samples.

This is a diagnostic, not a controller: the expert is the plant's own LQI law.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.plants.definition import Plant
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.metrics import step_metrics
from generalist_control.simulation.scenarios import references
from generalist_control.simulation.simulate import (
    PerPlantController,
    Run,
    Trajectory,
    simulate_many,
)

__all__ = ["HANDOVER_SAMPLES", "Handover", "handover_summary", "handover_table"]

#: Samples the expert controls before the policy takes over (0: the policy from the start).
HANDOVER_SAMPLES = (0, 1, 2, 5, 10, 20, 40)


class Handover:
    """The plants' LQI experts for the first ``after`` samples, then the policy.

    A :class:`~generalist_control.simulation.simulate.BatchController`. The policy's runtime
    is stepped at every sample and told the control the plant received, so it takes over
    from the expert's closed loop as if it had been running it.
    """

    def __init__(self, runtime: PolicyRuntime, after: int) -> None:
        if int(after) < 0:
            raise ValueError(f"after must be 0 or more samples; got {after}")
        self.runtime, self.after = runtime, int(after)

    def reset(self, plants: Sequence[Plant], counts: Sequence[int]) -> None:
        """One LQI expert per plant group, the policy over all rows."""
        self._expert = PerPlantController(LQIController)
        self._expert.reset(plants, counts)
        self._policy = RuntimeAdapter(self.runtime)
        self._policy.reset(plants, counts)
        self._k = 0

    def step(self, x: np.ndarray, r: np.ndarray) -> np.ndarray:
        """The expert's control before the hand-over, the policy's from it on."""
        u_e = self._expert.step(x, r)
        u_p = self._policy.step(x, r)  # NaN where the runtime refused the run
        u = u_e if self._k < self.after else u_p
        self._policy.record_applied(u)
        self._k += 1
        return u


def _ise(tr: Trajectory) -> np.ndarray:
    """Unit-step ISE per run; NaN for a diverged run."""
    ise = step_metrics(tr.t[:-1], tr.y[:, :-1], tr.u, tr.r)["ISE"]
    return np.where(tr.diverged, np.nan, ise)


def handover_table(
    runtime: PolicyRuntime,
    plants: Sequence[Plant],
    spec: Mapping[str, Any],
    samples: Sequence[int] = HANDOVER_SAMPLES,
) -> pd.DataFrame:
    """Per plant and hand-over sample, whether the policy diverged and its ISE ratio.

    Parameters
    ----------
    runtime : PolicyRuntime
        The policy as the evaluation runs it (with the tag withheld, for the tag-free bar).
    plants : sequence of Plant
    spec : mapping
        The step scenario (``conf/evaluation``'s ``step``: ``kind: step``, ``amplitude``,
        ``duration``).
    samples : sequence of int
        Hand-over samples ``N``.

    Returns
    -------
    DataFrame
        ``system, handover_samples, handover_s, diverged`` (runs diverged, of ``runs``),
        ``runs`` and ``ise_ratio`` (mean ISE of the hand-over runs over LQI's, over the whole
        run; NaN if any diverged).
    """
    runs = [Run(p, *references("step", spec, p)) for p in plants]
    lqi = [_ise(tr) for tr in simulate_many(runs, PerPlantController(LQIController))]
    rows = []
    for n in samples:
        trajs = simulate_many(runs, Handover(runtime, n))
        for p, tr, base in zip(plants, trajs, lqi, strict=True):
            ise = _ise(tr)
            rows.append(
                {
                    "system": p.name,
                    "handover_samples": int(n),
                    "handover_s": float(n * p.dt),
                    "diverged": int(np.sum(tr.diverged)),
                    "runs": int(tr.diverged.size),
                    "ise_ratio": float(np.mean(ise) / np.mean(base)),
                }
            )
    return pd.DataFrame(rows)


def handover_summary(table: pd.DataFrame, ise_ratio: float = 1.25) -> dict[str, Any]:
    """Per hand-over sample: plants diverged (named) and plants within ``ise_ratio``."""
    out: dict[str, Any] = {}
    for n, part in table.groupby("handover_samples"):
        lost = sorted(part.system[part.diverged > 0])
        out[str(n)] = {
            "handover_s": float(part.handover_s.iloc[0]),
            "plants_diverged": lost,
            "plants_within_ise_ratio": int((part.ise_ratio <= ise_ratio).sum()),
            "plants": int(len(part)),
        }
    return out
