"""The quality bar on its thresholds: a figure exactly at a limit passes, one ulp above fails.

Issue 36, item 6: no test sat on a threshold, so ``<=`` turned into ``<`` in
:func:`generalist_control.evaluation.summary.summarise` went unnoticed. The long-form metrics
below are built by hand with LQI's figures at 1.0, so each GC/LQI ratio is exactly the
figure given (a division by 1.0 is exact), and one value per metric makes each mean exact.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from generalist_control.evaluation.summary import DEFAULT_BAR, summarise

#: Verdict key -> (figure, its limit in the default bar).
THRESHOLDS = {
    "ISE_ratio_le_1.05": ("ise", DEFAULT_BAR["ISE_ratio"]),
    "ITAE_ratio_le_1.25": ("itae", DEFAULT_BAR["ITAE_ratio"]),
    "RMSE_ratio_le_1.1": ("rmse", DEFAULT_BAR["RMSE_ratio"]),
    "ess_within_0.5pct": ("ess", DEFAULT_BAR["relative_ess"]),
    "GC_AW_no_worse_than_LQI_AW": ("aw", 1.0 + DEFAULT_BAR["anti_windup_tolerance"]),
}
GOOD = {"ise": 1.0, "itae": 1.0, "rmse": 1.0, "ess": 0.0, "aw": 1.0}


def _metrics(ise: float, itae: float, rmse: float, ess: float, aw: float) -> pd.DataFrame:
    """One plant: the unit step, a tracking scenario and the anti-windup one, LQI at 1.0."""
    rows = [
        ("step", "GC", "ISE", ise),
        ("step", "GC", "ITAE", itae),
        ("step", "GC", "rise_time", 1.0),
        ("step", "GC", "relative_steady_state_error", ess),
        ("step", "LQI", "ISE", 1.0),
        ("step", "LQI", "ITAE", 1.0),
        ("step", "LQI", "rise_time", 1.0),
        ("step", "LQI", "relative_steady_state_error", 0.0),
        ("sine", "GC", "RMSE", rmse),
        ("sine", "LQI", "RMSE", 1.0),
        ("saturation_0.25", "GC-AW", "ISE", aw),
        ("saturation_0.25", "LQI-AW", "ISE", 1.0),
    ]
    return pd.DataFrame(
        [("p", scen, ctrl, 0, metric, value) for scen, ctrl, metric, value in rows],
        columns=["system", "scenario", "controller", "run", "metric", "value"],
    )


@pytest.mark.parametrize("verdict", list(THRESHOLDS))
def test_a_figure_exactly_at_its_limit_passes_and_just_above_fails(verdict):
    figure, limit = THRESHOLDS[verdict]
    at = summarise(_metrics(**{**GOOD, figure: limit}))["quality_bar"]
    above = summarise(_metrics(**{**GOOD, figure: np.nextafter(limit, np.inf)}))["quality_bar"]
    assert at == {**{k: True for k in THRESHOLDS}, "stable_everywhere": True}
    assert above[verdict] is False
    assert all(v is True for k, v in above.items() if k != verdict)  # only that one fails


def test_the_thresholds_are_the_ones_the_verdicts_name():
    """The figures above sit on the limits the bar's keys print (1.05, 1.25, 1.1, 0.5 %)."""
    assert (DEFAULT_BAR["ISE_ratio"], DEFAULT_BAR["ITAE_ratio"]) == (1.05, 1.25)
    assert (DEFAULT_BAR["RMSE_ratio"], DEFAULT_BAR["relative_ess"]) == (1.1, 0.005)
    summary = summarise(_metrics(**GOOD))
    assert summary["ratios"]["step"]["worst_ISE_ratio"] == 1.0
    assert summary["anti_windup"]["saturation_0.25"]["worst_ISE_ratio"] == 1.0
