"""The tag-free bar (issue 13) and its report: what the policy without its tag achieves.

From the long-form metrics of an evaluation of a policy without the tag
(``experiment=tag_free``: its plant part never reads the tag), :func:`tag_free_bar` checks

* no divergence of GC on any plant in any scenario;
* the unit-step ISE ratio GC/LQI at most ``ise_ratio`` (1.25) on at least ``min_plants``
  (20) of the plants;

and, for the plants that miss, :func:`write_tag_free_report` adds how soon the history tells
each plant apart (:func:`~analysis.separation.separation_table`), a
figure of the first samples the network sees for the plant and its nearest neighbour, and,
given the evaluation's trajectories, when each diverged run left its expert
(:func:`~analysis.departures.departure_table`, ``departures.csv``)
and, given a hand-over table, whether the plant's own expert making the first controls
saves the missed plants (:mod:`~analysis.handover`, ``handover.csv``),
and given local gains, how the policy's feedback compares with LQI's
(:mod:`~analysis.local_gains`, ``gains.csv``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from analysis.departures import (  # noqa: E402
    departure_summary,
    departure_table,
)
from analysis.handover import handover_summary  # noqa: E402
from analysis.identity import (  # noqa: E402
    identity_summary,
    identity_table,
)
from analysis.local_gains import gain_summary  # noqa: E402
from analysis.separation import (  # noqa: E402
    network_views,
    separation_table,
)
from generalist_control.common.atomic import (  # noqa: E402
    check_replaceable,
    publish_directory,
    staging_directory,
)
from generalist_control.common.jsonsafe import write_json  # noqa: E402
from generalist_control.model.plant import InferredPlant  # noqa: E402
from generalist_control.model.policy import Policy  # noqa: E402
from generalist_control.plants.definition import Plant  # noqa: E402
from generalist_control.simulation.simulate import Trajectory  # noqa: E402

__all__ = [
    "OWNED",
    "check_tag_free_dir",
    "tag_free_bar",
    "write_tag_free_report",
]

#: What a tag-free report folder holds (the only entries a new report may replace).
OWNED: dict[str, str | None] = {
    "bar.json": None,
    "separation.csv": None,
    "departures.csv": None,
    "handover.csv": None,
    "gains.csv": None,
    "identity.csv": None,
    "identity_trace.csv": None,
    "plots": "*.png",
}


def check_tag_free_dir(out_dir: str | Path) -> None:
    """Refuse (before any work) a report folder that holds other files."""
    check_replaceable(out_dir, OWNED, "+analysis.out")


def _values(df: pd.DataFrame, scenario: str | None, controller: str, metric: str) -> pd.Series:
    """Per system, the mean of ``metric`` for ``controller`` (in ``scenario`` if given)."""
    sel = (df.controller == controller) & (df.metric == metric)
    if scenario is not None:
        sel &= df.scenario == scenario
    return df[sel].groupby("system")["value"].mean()


def tag_free_bar(
    df: pd.DataFrame, ise_ratio: float = 1.25, min_plants: int = 20
) -> dict[str, Any]:
    """The tag-free bar from an evaluation's long-form metrics (tag withheld).

    Returns
    -------
    dict
        ``diverged`` (``system/scenario`` pairs where GC diverged), ``step_ise_ratio`` per
        plant, ``missing`` (plants above ``ise_ratio``), ``passed`` (plants at or below) and
        the verdicts ``no_divergence``, ``step_ise_ratio`` and ``met`` (both).
    """
    gc = df[(df.controller == "GC") & (df.metric == "diverged") & (df.value > 0)]
    diverged = sorted({f"{s}/{c}" for s, c in zip(gc.system, gc.scenario, strict=True)})
    ratio = (_values(df, "step", "GC", "ISE") / _values(df, "step", "LQI", "ISE")).dropna()
    missing = sorted(ratio[~(ratio <= ise_ratio)].index)
    passed = len(ratio) - len(missing)
    return {
        "diverged": diverged,
        "step_ise_ratio": {k: float(v) for k, v in sorted(ratio.items())},
        "ise_ratio_bar": ise_ratio,
        "min_plants": min_plants,
        "missing": missing,
        "passed": passed,
        "plants": int(len(ratio)),
        "no_divergence": not diverged,
        "step_ise_ratio_met": passed >= min(min_plants, len(ratio)),
        "met": not diverged and passed >= min(min_plants, len(ratio)),
    }


def _figure(
    views: tuple[np.ndarray, np.ndarray],
    plants: Sequence[Plant],
    pairs: list[tuple[str, str]],
    path: Path,
) -> None:
    """First samples of what the network sees (input norm) and must answer, plant by pair."""
    if not pairs:
        return
    index = {p.name: i for i, p in enumerate(plants)}
    inputs, controls = views
    t = np.arange(inputs.shape[1]) * plants[0].dt
    fig, axes = plt.subplots(len(pairs), 2, figsize=(10, 2.6 * len(pairs)), squeeze=False)
    for row, (a, b) in enumerate(pairs):
        for name, style in ((a, "-"), (b, "--")):
            i = index[name]
            axes[row, 0].plot(t, np.linalg.norm(inputs[i], axis=1), style, label=name)
            axes[row, 1].plot(t, controls[i], style, label=name)
        axes[row, 0].set_ylabel("|network input|")
        axes[row, 1].set_ylabel("expert control (learned units)")
        axes[row, 0].legend(fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time after a unit step from rest (s)")
    fig.suptitle("Without the tag: missed plants and the plant they look like at first")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _handover_figure(table: pd.DataFrame, verdict: dict[str, Any], path: Path) -> None:
    """Missed plants' unit-step ISE ratio against the samples the expert made first."""
    missed = [s for s in verdict["missing"] if s in set(table.system)]
    if not missed:
        return
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name in missed:
        part = table[table.system == name].sort_values("handover_s")
        ratio = part.ise_ratio.where(part.diverged == 0)  # a diverged run draws no point
        ax.plot(part.handover_s, ratio, "o-", label=name)
    ax.axhline(verdict["ise_ratio_bar"], color="k", ls=":", lw=1)
    lost = table.groupby("system").diverged.min()  # diverged whoever made the first controls
    if (lost > 0).any():
        ax.set_title(f"diverged at every hand-over: {', '.join(lost.index[lost > 0])}", fontsize=9)
    ax.set_xscale("symlog", linthresh=0.05)
    ax.set_xlim(left=0.0)
    ax.set_yscale("log")
    ax.set_xlabel("expert's controls before the policy takes over (s)")
    ax.set_ylabel("unit-step ISE GC / LQI (no point: diverged)")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _diagnostic_tables(
    verdict: dict[str, Any],
    policy: Policy,
    plants: Sequence[Plant],
    trajectories: Mapping[str, Mapping[str, Mapping[str, Trajectory]]] | None,
    handover: pd.DataFrame | None,
    gains: pd.DataFrame | None,
) -> dict[str, pd.DataFrame | None]:
    """The departure, hand-over, gain and identity tables (None: not given).

    Their summaries (but the identity's) go into ``verdict``.
    """
    left = departure_table(trajectories) if trajectories is not None else None
    if left is not None:
        verdict["departures"] = departure_summary(left)
    if handover is not None:
        verdict["handover"] = handover_summary(handover, verdict["ise_ratio_bar"])
    if gains is not None:
        verdict["local_gains"] = gain_summary(gains)
    inferred = isinstance(policy.net.plant, InferredPlant)
    named = identity_table(policy, plants) if inferred else None
    return {
        "departures.csv": left,
        "handover.csv": handover,
        "gains.csv": gains,
        "identity.csv": named,
    }


def write_tag_free_report(
    df: pd.DataFrame,
    policy: Policy,
    plants: Sequence[Plant],
    out_dir: str | Path,
    bar: dict[str, Any] | None = None,
    trajectories: Mapping[str, Mapping[str, Mapping[str, Trajectory]]] | None = None,
    handover: pd.DataFrame | None = None,
    gains: pd.DataFrame | None = None,
    identity_trace: pd.DataFrame | None = None,
) -> dict[str, Any]:
    """Write ``bar.json``, ``separation.csv`` and ``plots/`` to ``out_dir``; return the bar.

    ``bar`` overrides ``ise_ratio`` and ``min_plants`` of :func:`tag_free_bar`. With the
    evaluation's ``trajectories`` it also writes ``departures.csv`` (when each diverged GC
    run left its expert) and its counts as ``departures`` in the bar; with a ``handover``
    table (:func:`~analysis.handover.handover_table`) ``handover.csv``,
    its summary as ``handover`` in the bar and a figure of the missed plants' ISE ratios;
    with ``gains`` (:func:`~analysis.local_gains.local_gains`)
    ``gains.csv`` and, per plant,
    :func:`~analysis.local_gains.gain_summary` as ``local_gains`` in
    the bar. A policy with an identity head (``model.plant: inferred``) also gets
    ``identity.csv`` (:func:`~analysis.identity.identity_table`) and
    its :func:`~analysis.identity.identity_summary` as ``identity`` in
    the bar; with an ``identity_trace``
    (:func:`~analysis.identity.identity_trace`) ``identity_trace.csv``.
    """
    check_tag_free_dir(out_dir)
    verdict = tag_free_bar(df, **(bar or {}))
    views = network_views(policy, plants, duration=2.0)
    table = separation_table(policy, plants, duration=2.0, views=views)
    ratio = verdict["step_ise_ratio"]
    table["step_ise_ratio"] = table.system.map(ratio)
    missing = table[table.system.isin(verdict["missing"])]
    verdict["why_missed"] = missing.to_dict(orient="records")
    pairs = list(zip(missing.system, missing.nearest, strict=True))
    tables = {
        "separation.csv": table,
        **_diagnostic_tables(verdict, policy, plants, trajectories, handover, gains),
        "identity_trace.csv": identity_trace,
    }
    if tables["identity.csv"] is not None:
        verdict["identity"] = identity_summary(tables["identity.csv"], identity_trace)
    with staging_directory(out_dir) as staging:
        for name, frame in tables.items():
            if frame is not None:
                frame.to_csv(staging / name, index=False)
        write_json(staging / "bar.json", verdict, sort_keys=True)
        (staging / "plots").mkdir()
        _figure(views, plants, pairs, staging / "plots" / "tag_free_missed.png")
        if handover is not None:
            _handover_figure(handover, verdict, staging / "plots" / "tag_free_handover.png")
        publish_directory(staging, out_dir, OWNED, "+analysis.out")
    return verdict
