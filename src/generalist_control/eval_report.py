"""Tables, plots and MLflow logging of the closed-loop evaluation (see ``evaluate``)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from generalist_control.paper import TABLE2, TABLE2_COLUMNS, TABLE2_METRICS  # noqa: E402
from generalist_control.simulate import Trajectory  # noqa: E402

__all__ = [
    "log_to_mlflow",
    "plot_all",
    "recipes_markdown",
    "responses_csv",
    "table2_markdown",
    "table_all_markdown",
]

_STYLE = {
    "GC": ("tab:blue", "-"),
    "LQI": ("tab:orange", "--"),
    "LQI-AW": ("tab:green", ":"),
    "GC-AW": ("tab:purple", "-."),
}


def _fmt(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"


def _step_means(df: pd.DataFrame, scenario: str = "step") -> pd.Series:
    d = df[df.scenario == scenario]
    return d.groupby(["controller", "system", "metric"])["value"].mean()


def table2_markdown(df: pd.DataFrame) -> str:
    """The paper's Table 2 layout for the paper systems present: paper values beside ours."""
    means = _step_means(df)
    systems = [s for s in TABLE2_COLUMNS if ("GC", s, "ISE") in means.index]
    if not systems:
        return "No system of the paper's Table 2 was evaluated.\n"
    head = ["Metric", *(TABLE2_COLUMNS[s] for s in systems)]
    lines = [
        "# Unit-step metrics: the paper's Table 2 beside ours",
        "",
        "Unit step from rest, dt = 0.05 s. *paper*: Agyei & Sarhadi 2026, Table 2. "
        "A diverged run shows as `diverged`.",
        "",
        "| " + " | ".join(head) + " |",
        "| " + " | ".join(["---"] + ["---:"] * len(systems)) + " |",
    ]
    for metric, symbol in TABLE2_METRICS.items():
        for ctrl in ("LQI", "GC"):
            paper = [_fmt(TABLE2[ctrl][s][metric]) for s in systems]
            ours = []
            for s in systems:
                if means.get((ctrl, s, "diverged"), 0) > 0:
                    ours.append("diverged")
                else:
                    ours.append(_fmt(means.get((ctrl, s, metric), np.nan)))
            lines.append(f"| {symbol} ({ctrl}) paper | " + " | ".join(paper) + " |")
            lines.append(f"| {symbol} ({ctrl}) ours | " + " | ".join(ours) + " |")
    return "\n".join(lines) + "\n"


def table_all_markdown(df: pd.DataFrame) -> str:
    """Every plant: GC and LQI unit-step metrics, ratios, and random-step results."""
    means = _step_means(df)
    rnd = _step_means(df, "random_steps")
    systems = sorted(df.system.unique())
    cols = ["t_r", "M_p", "t_s", "e_ss", "ISE", "ITAE", "u_max"]
    head = [
        "system",
        *(f"{c} GC/LQI" for c in cols),
        "ISE ratio",
        "ITAE ratio",
        "random: ISE ratio",
        "random: max rel. e_ss GC",
        "diverged GC",
    ]
    lines = [
        "# Unit-step and random-step metrics, all plants (GC / LQI)",
        "",
        "| " + " | ".join(head) + " |",
        "| " + " | ".join(["---"] + ["---:"] * (len(head) - 1)) + " |",
    ]
    d = df[(df.controller == "GC") & (df.metric == "diverged")].groupby("system")["value"].sum()
    rel = (
        df[
            (df.scenario == "random_steps")
            & (df.controller == "GC")
            & (df.metric == "relative_steady_state_error")
        ]
        .groupby("system")["value"]
        .max()
    )
    for s in systems:

        def get(c: str, m: str, src: pd.Series = means, s: str = s) -> float:
            return src.get((c, s, m), np.nan)

        cells = [f"{_fmt(get('GC', m))} / {_fmt(get('LQI', m))}" for m in TABLE2_METRICS]
        cells += [_fmt(get("GC", k) / get("LQI", k)) for k in ("ISE", "ITAE")]
        cells.append(_fmt(get("GC", "ISE", rnd) / get("LQI", "ISE", rnd)))
        cells.append(_fmt(rel.get(s, np.nan)))
        cells.append(str(int(d.get(s, 0))))
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def recipes_markdown(results: Mapping[str, pd.DataFrame]) -> str:
    """Per plant, the quality-bar figures of several evaluations side by side.

    Parameters
    ----------
    results : mapping
        Label (e.g. ``"paper"``, ``"ours"``) -> long-form metrics of an evaluation
        (``metrics.csv``).
    """
    labels = list(results)
    head = ["system"]
    for what in ("ISE ratio", "ITAE ratio", "e_ss (rel.)", "random: worst rel. e_ss", "diverged"):
        head += [f"{what} {label}" for label in labels]
    per: dict[str, dict[str, pd.Series]] = {}
    for label, df in results.items():
        gc = df[df.controller == "GC"]
        means = _step_means(df)
        step_rel = gc[(gc.scenario == "step") & (gc.metric == "relative_steady_state_error")]
        rnd_rel = gc[
            (gc.scenario == "random_steps") & (gc.metric == "relative_steady_state_error")
        ]
        div = gc[(gc.metric == "diverged") & gc.scenario.isin(["step", "random_steps"])]
        per[label] = {
            "ISE": means.get("GC", pd.Series(dtype=float)).xs("ISE", level="metric")
            / means["LQI"].xs("ISE", level="metric"),
            "ITAE": means.get("GC", pd.Series(dtype=float)).xs("ITAE", level="metric")
            / means["LQI"].xs("ITAE", level="metric"),
            "ess": step_rel.groupby("system")["value"].mean(),
            "rnd": rnd_rel.groupby("system")["value"].max(),
            "div": div.groupby("system")["value"].sum(),
        }
    systems = sorted(set().union(*(set(df.system) for df in results.values())))
    lines = [
        "| " + " | ".join(head) + " |",
        "| " + " | ".join(["---"] + ["---:"] * (len(head) - 1)) + " |",
    ]
    for s in systems:
        cells = [s]
        for key in ("ISE", "ITAE", "ess", "rnd", "div"):
            for label in labels:
                v = per[label][key].get(s, np.nan)
                cells.append(str(int(v)) if key == "div" else _fmt(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def responses_csv(trajs: Mapping[str, Mapping[str, Mapping[str, Trajectory]]]) -> pd.DataFrame:
    """Unit-step responses in long form (DVC plots): system, controller, t, r, y, u."""
    frames = []
    for ctrl, by_system in trajs.get("step", {}).items():
        for system, tr in by_system.items():
            n = tr.u.shape[1]
            frames.append(
                pd.DataFrame(
                    {
                        "system": system,
                        "controller": ctrl,
                        "t": tr.t[:n],
                        "r": tr.r[0],
                        "y": tr.y[0, :n],
                        "u": tr.u[0],
                    }
                )
            )
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _panel(ax_y, ax_u, by_ctrl: Mapping[str, Trajectory], controllers: tuple[str, ...]) -> None:
    ref = next(iter(by_ctrl.values()))
    n = ref.u.shape[1]
    ax_y.plot(ref.t[:n], ref.r[0], color="0.4", lw=1, label="reference")
    for ctrl in controllers:
        tr = by_ctrl.get(ctrl)
        if tr is None:
            continue
        color, ls = _STYLE[ctrl]
        label = ctrl + (" (diverged)" if tr.diverged[0] else "")
        ax_y.plot(tr.t[:n], tr.y[0, :n], color=color, ls=ls, label=label)
        ax_u.plot(tr.t[:n], tr.u[0], color=color, ls=ls)
    ax_y.set_ylabel("y")
    ax_u.set_ylabel("u")
    ax_u.set_xlabel("t (s)")
    ax_y.legend(fontsize=7)
    for ax in (ax_y, ax_u):
        ax.grid(alpha=0.3)


def plot_all(trajs: Mapping[str, Mapping[str, Mapping[str, Trajectory]]], out: Path) -> list[Path]:
    """Step and sine responses per plant (GC vs LQI), and each perturbation run."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    systems = sorted(trajs.get("step", {}).get("GC", {}))
    for s in systems:
        fig, axes = plt.subplots(2, 2, figsize=(10, 5.5), sharex="col")
        for col, scen in enumerate(("step", "sine")):
            by_ctrl = {
                c: trajs[scen][c][s] for c in ("GC", "LQI") if s in trajs.get(scen, {}).get(c, {})
            }
            if by_ctrl:
                _panel(axes[0, col], axes[1, col], by_ctrl, ("GC", "LQI"))
                axes[0, col].set_title(f"{s}: {scen}")
        # fixed margins: tight_layout doubles the drawing time of the evaluation's plots
        fig.subplots_adjust(left=0.08, right=0.98, bottom=0.1, top=0.94, wspace=0.18, hspace=0.1)
        path = out / f"{s}_step_sine.png"
        fig.savefig(path, dpi=80)
        plt.close(fig)
        written.append(path)
    for scen, by_ctrl in trajs.items():
        if scen in ("step", "sine", "ramp", "composite", "random_steps"):
            continue
        for s in by_ctrl.get("GC", {}):
            fig, (ax_y, ax_u) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
            order = tuple(c for c in ("GC", "GC-AW", "LQI", "LQI-AW") if c in by_ctrl)
            _panel(ax_y, ax_u, {c: by_ctrl[c][s] for c in by_ctrl}, order)
            ax_y.set_title(f"{s}: {scen}")
            fig.subplots_adjust(left=0.11, right=0.97, bottom=0.1, top=0.94, hspace=0.08)
            path = out / f"{s}_{scen}.png"
            fig.savefig(path, dpi=80)
            plt.close(fig)
            written.append(path)
    return written


def log_to_mlflow(
    cfg: Any, meta: Mapping[str, Any], summary: Mapping[str, Any], out_dir: Path
) -> str | None:
    """Log the summary figures and the report folder to the evaluated model's MLflow run."""
    import mlflow

    from generalist_control.mlflow_utils import mlflow_run

    flat: dict[str, float] = {}
    for scen, vals in summary.get("ratios", {}).items():
        for k, v in vals.items():
            if isinstance(v, (int, float)) and math.isfinite(v):
                flat[f"eval/{scen}/{k}"] = float(v)
    for ctrl, by_scen in summary.get("diverged", {}).items():
        flat[f"eval/diverged/{ctrl}"] = float(sum(by_scen.values()))
    with mlflow_run(cfg.logger, resume_run_id=meta.get("mlflow_run_id")) as run:
        mlflow.log_metrics(flat)
        mlflow.log_artifacts(str(out_dir), "eval")
        return run.info.run_id
