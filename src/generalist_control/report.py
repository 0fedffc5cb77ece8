"""The ablation report (paper, Section 7) redrawn from the MLflow training runs.

Run ``python -m generalist_control.report`` (Hydra; settings in ``conf/report``) or
``dvc repro report``. Nothing is trained here: the report reads the finished training runs
of one MLflow experiment, each of which carries ``model.hidden`` and ``experts`` (params),
``n_parameters``, the per-epoch ``train/loss`` history and ``closed_loop/mse/<plant>``, the
GC-vs-LQI unit-step output MSE on the ablation set. The two sweeps are

* the hidden dimension ``d`` in ``report.hidden`` at ``M = report.baseline.experts``
  (created by ``python train.py -m model.hidden=16,32,64``), and
* the expert count ``M`` in ``report.experts`` at ``d = report.baseline.hidden``
  (``python train.py -m experts=1,3,5``);

when several runs share a configuration the newest one is used. A configuration without a
run is drawn and tabulated as "no run"; an experiment without any finished training run is
an error (:class:`NoAblationRunsError`) that names the commands above.

Outputs under ``report.out_dir`` (``reports/ablation``), written to a temporary directory
and renamed into place, a PNG and a CSV for each figure:

* ``mse_hidden``, ``mse_experts``: per-plant closed-loop output MSE (grouped bars, log y);
* ``loss_hidden``, ``loss_experts``: training-loss curves (``train/loss`` per epoch);
* ``params_vs_mse``: parameter count against the mean MSE over the plants;
* ``gate_weights``: mean gate weight per expert and plant of the ``M = report.gate.experts``
  model (see :func:`gate_weights` for how the weights are gathered);
* ``fig_hidden_ablation.png``, ``fig_expert_ablation.png``: the paper's two-panel layouts;
* ``comparison.md`` (our figures beside the paper's, :data:`generalist_control.paper.ABLATION`),
  ``runs.csv`` (the runs used) and ``summary.json``.

Everything is logged to a ``report`` run of the same experiment (tag ``gc.run_type =
report``), which the run search leaves out. The drawing functions take a Matplotlib
``Axes`` and data frames, so notebooks reuse them (``notebooks/02_mlflow_comparison.ipynb``).
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator
from omegaconf import DictConfig, OmegaConf

from generalist_control.paper import ABLATION
from generalist_control.paths import HYDRA_CONFIG_PATH

__all__ = [
    "RUN_TYPE_TAG",
    "SWEEP_COMMANDS",
    "NoAblationRunsError",
    "RunPoint",
    "comparison_markdown",
    "draw_gate_heatmap",
    "draw_loss_curves",
    "draw_mse_bars",
    "draw_params_vs_mse",
    "gate_weights",
    "loss_frame",
    "mse_frame",
    "params_frame",
    "policy_of_run",
    "run",
    "runs_from_mlflow",
    "runs_table",
    "select_sweeps",
    "write_report",
]

log = logging.getLogger(__name__)

#: The commands that create the sweep runs (quoted when there are none).
SWEEP_COMMANDS = (
    "python train.py -m model.hidden=16,32,64",
    "python train.py -m experts=1,3,5",
)
#: Tag that marks runs written by this module (left out of the run search).
RUN_TYPE_TAG = "gc.run_type"
#: Tag of sweep and study parent runs (:mod:`generalist_control.sweep`): ``sweep`` or ``study``.
ROLE_TAG = "gc.role"
#: Sweep name -> (run attribute, symbol used in labels).
SWEEPS = {"hidden": "d", "experts": "M"}
NO_RUN = "no run"
NOT_AVAILABLE = "no score"
POLICY_ARTIFACT = "policy/policy.ckpt"


class NoAblationRunsError(LookupError):
    """The MLflow experiment holds no finished training run to report on."""


@dataclass(frozen=True)
class RunPoint:
    """The figures of one finished training run that the report needs.

    Attributes
    ----------
    run_id, run_name : str
    hidden, experts : int
        ``model.hidden`` (d) and ``experts`` (M).
    n_parameters : int or None
    train_loss : float or None
        The last logged ``train/loss`` (the final training loss).
    mse : dict
        ``closed_loop/mse/<plant>`` by plant (only finite scores are logged by training).
    diverged : int
        ``closed_loop/diverged``: plants whose GC closed loop diverged (no score logged).
    start_time : int
        Milliseconds since the epoch.
    """

    run_id: str
    run_name: str
    hidden: int
    experts: int
    n_parameters: int | None
    train_loss: float | None
    mse: dict[str, float] = field(default_factory=dict)
    diverged: int = 0
    start_time: int = 0

    @property
    def label(self) -> str:
        """``d=<hidden>,M=<experts>``, the key format of :data:`paper.ABLATION`."""
        return f"d={self.hidden},M={self.experts}"


def _as_int(text: str | None) -> int | None:
    try:
        return int(float(text)) if text is not None else None
    except ValueError:
        return None


def _point(run: Any) -> RunPoint | None:
    """A :class:`RunPoint` for an MLflow run, or None if it is no training run."""
    params, metrics, tags = run.data.params, run.data.metrics, run.data.tags
    if tags.get(RUN_TYPE_TAG) == "report":
        return None
    hidden, experts = _as_int(params.get("model.hidden")), _as_int(params.get("experts"))
    if hidden is None or experts is None:
        return None
    prefix = "closed_loop/mse/"
    mse = {k[len(prefix) :]: float(v) for k, v in metrics.items() if k.startswith(prefix)}
    n_params = _as_int(params.get("n_parameters"))
    if n_params is None and "n_parameters" in metrics:
        n_params = int(metrics["n_parameters"])
    loss = metrics.get("train/loss")
    return RunPoint(
        run_id=run.info.run_id,
        run_name=run.info.run_name or "",
        hidden=hidden,
        experts=experts,
        n_parameters=n_params,
        train_loss=float(loss) if loss is not None else None,
        mse=mse,
        diverged=int(metrics.get("closed_loop/diverged", 0) or 0),
        start_time=int(run.info.start_time or 0),
    )


def _client(tracking_uri: str | None = None) -> Any:
    from mlflow.tracking import MlflowClient

    return MlflowClient(tracking_uri=tracking_uri)


def runs_from_mlflow(
    experiment_name: str,
    filter_string: str = "",
    client: Any | None = None,
) -> list[RunPoint]:
    """Training runs of an MLflow experiment, newest first.

    Parameters
    ----------
    experiment_name : str
    filter_string : str
        An MLflow search filter, e.g. ``"attributes.status = 'FINISHED'"``.
    client : mlflow.tracking.MlflowClient, optional
        Default: a client on the current tracking URI.

    Returns
    -------
    list of RunPoint
        Runs with ``model.hidden`` and ``experts`` params. Left out: report runs, the parent
        runs of sweeps and studies (tag ``gc.role``) and the trials of Optuna studies (their
        hyperparameters are not the baseline's); the jobs of a multirun sweep are kept. An
        unknown experiment gives an empty list.
    """
    client = client or _client()
    experiment = client.get_experiment_by_name(experiment_name)
    if experiment is None:
        return []
    points, token = [], None
    roles: dict[str, str | None] = {}  # parent run id -> its gc.role tag

    def parent_role(run: Any) -> str | None:
        parent = run.data.tags.get("mlflow.parentRunId")
        if not parent:
            return None
        if parent not in roles:
            try:
                roles[parent] = client.get_run(parent).data.tags.get(ROLE_TAG)
            except Exception:  # noqa: BLE001 (a deleted parent: keep the run)
                roles[parent] = None
        return roles[parent]

    while True:
        page = client.search_runs(
            [experiment.experiment_id],
            filter_string=filter_string or "",
            order_by=["attributes.start_time DESC"],
            max_results=1000,
            page_token=token,
        )
        for run in page:
            if run.data.tags.get(ROLE_TAG) or parent_role(run) == "study":
                continue  # a sweep/study parent, or a trial of an Optuna study
            point = _point(run)
            if point is not None:
                points.append(point)
        token = page.token
        if not token:
            break
    return sorted(points, key=lambda p: -p.start_time)


def select_sweeps(
    points: Sequence[RunPoint],
    hidden: Sequence[int] = (16, 32, 64),
    experts: Sequence[int] = (1, 3, 5),
    baseline: Mapping[str, int] | None = None,
) -> dict[str, dict[int, RunPoint | None]]:
    """The run of each sweep point: the newest matching run, or None ("no run").

    Parameters
    ----------
    points : sequence of RunPoint
        Newest first (as :func:`runs_from_mlflow` returns them).
    hidden, experts : sequence of int
        The values of d (at the baseline M) and of M (at the baseline d).
    baseline : mapping, optional
        ``{"hidden": 32, "experts": 3}`` (the default).

    Returns
    -------
    dict
        ``{"hidden": {d: RunPoint | None}, "experts": {M: RunPoint | None}}``.
    """
    base = {"hidden": 32, "experts": 3, **(baseline or {})}
    newest = sorted(points, key=lambda p: -p.start_time)

    def first(d: int, m: int) -> RunPoint | None:
        return next((p for p in newest if p.hidden == d and p.experts == m), None)

    return {
        "hidden": {int(d): first(int(d), int(base["experts"])) for d in hidden},
        "experts": {int(m): first(int(base["hidden"]), int(m)) for m in experts},
    }


def _unique_points(sweeps: Mapping[str, Mapping[int, RunPoint | None]]) -> list[RunPoint]:
    seen: dict[str, RunPoint] = {}
    for by_value in sweeps.values():
        for p in by_value.values():
            if p is not None:
                seen.setdefault(p.run_id, p)
    return sorted(seen.values(), key=lambda p: (p.hidden, p.experts))


def _label(sweep: str, value: int) -> str:
    return f"{SWEEPS[sweep]}={value}"


def mse_frame(
    sweeps: Mapping[str, Mapping[int, RunPoint | None]], plants: Sequence[str]
) -> pd.DataFrame:
    """Per-plant closed-loop MSE of every sweep point, long form.

    Returns
    -------
    DataFrame
        Columns ``sweep, value, label, plant, mse, status, run_id``; ``status`` is ``ok``,
        ``no run`` (no run for the point) or ``no score`` (the run has no score for the plant:
        its closed loop diverged or it was not trained on the plant).
    """
    rows = []
    for sweep, by_value in sweeps.items():
        for value, p in by_value.items():
            for plant in plants:
                mse = p.mse.get(plant) if p is not None else None
                status = NO_RUN if p is None else ("ok" if mse is not None else NOT_AVAILABLE)
                rows.append(
                    (sweep, value, _label(sweep, value), plant, mse, status, p and p.run_id)
                )
    cols = ["sweep", "value", "label", "plant", "mse", "status", "run_id"]
    df = pd.DataFrame(rows, columns=cols)
    df["mse"] = df["mse"].astype(float)
    return df


def loss_frame(
    sweeps: Mapping[str, Mapping[int, RunPoint | None]], client: Any | None = None
) -> pd.DataFrame:
    """Training-loss history (``train/loss`` per epoch) of every sweep point, long form.

    Returns
    -------
    DataFrame
        Columns ``sweep, value, label, run_id, epoch, train_loss``; a point without a run
        has no rows. Of repeated steps (a resumed run) the latest value is kept.
    """
    client = client or _client()
    frames = []
    cache: dict[str, pd.DataFrame] = {}
    for sweep, by_value in sweeps.items():
        for value, p in by_value.items():
            if p is None:
                continue
            if p.run_id not in cache:
                hist = client.get_metric_history(p.run_id, "train/loss")
                h = pd.DataFrame(
                    [(m.step, m.timestamp, m.value) for m in hist],
                    columns=["epoch", "timestamp", "train_loss"],
                )
                h = h.sort_values(["epoch", "timestamp"]).drop_duplicates("epoch", keep="last")
                cache[p.run_id] = h.drop(columns="timestamp")
            h = cache[p.run_id].copy()
            h.insert(0, "run_id", p.run_id)
            h.insert(0, "label", _label(sweep, value))
            h.insert(0, "value", value)
            h.insert(0, "sweep", sweep)
            frames.append(h)
    cols = ["sweep", "value", "label", "run_id", "epoch", "train_loss"]
    if not frames:
        return pd.DataFrame(columns=cols)
    return pd.concat(frames, ignore_index=True)[cols]


def params_frame(
    sweeps: Mapping[str, Mapping[int, RunPoint | None]], plants: Sequence[str]
) -> pd.DataFrame:
    """Parameter count and mean closed-loop MSE of every distinct run of the sweeps.

    The mean is over the plants of ``plants`` that the run has a score for (``n_plants``).

    Returns
    -------
    DataFrame
        Columns ``label, hidden, experts, n_parameters, mse_mean, n_plants, final_train_loss,
        run_id``.
    """
    rows = []
    for p in _unique_points(sweeps):
        scores = [p.mse[k] for k in plants if k in p.mse]
        mean = float(np.mean(scores)) if scores else np.nan
        rows.append(
            (
                p.label,
                p.hidden,
                p.experts,
                p.n_parameters,
                mean,
                len(scores),
                p.train_loss,
                p.run_id,
            )
        )
    cols = [
        "label",
        "hidden",
        "experts",
        "n_parameters",
        "mse_mean",
        "n_plants",
        "final_train_loss",
        "run_id",
    ]
    return pd.DataFrame(rows, columns=cols)


def policy_of_run(run_id: str, client: Any | None = None) -> tuple[Any, dict[str, Any]]:
    """Download a run's ``policy/policy.ckpt`` artifact and load it (``weights_only``)."""
    from generalist_control.policy import load_policy

    client = client or _client()
    with tempfile.TemporaryDirectory(prefix="gc-policy-") as tmp:
        path = client.download_artifacts(run_id, POLICY_ARTIFACT, tmp)
        return load_policy(path)


def gate_weights(
    policy: Any,
    meta: Mapping[str, Any],
    plants: Iterable[str] | None = None,
    duration: float = 15.0,
) -> pd.DataFrame:
    """Mean gate weight per expert and plant over closed-loop unit-step runs.

    Each plant runs the policy in closed loop (the deployment runtime,
    :class:`~generalist_control.runtime.PolicyRuntime`) on a unit step from rest, scaled by
    its ``amplitude_scale`` as in evaluation, for ``duration`` seconds. The states and
    references the runtime saw are turned back into its input windows by the project's
    window builder (:func:`~generalist_control.windows.history_windows`, which pads the
    first sample exactly as the runtime fills its buffer), and the gate weights the policy
    gives those windows are averaged over the run. The weights are therefore those of the
    policy at work on the plant, not on the expert's demonstrations.

    Parameters
    ----------
    policy : Policy
    meta : mapping
        The policy's metadata (``tags``, ``orders``, ``history``, ``horizon``, ``dt``).
    plants : iterable of str, optional
        Default: every plant of the catalogue the policy was trained on, in tag order.
    duration : float

    Returns
    -------
    DataFrame
        Index: plant (name); columns ``expert_1 .. expert_M``; rows sum to one.
    """
    from generalist_control.catalog import available_plants, load_plant
    from generalist_control.runtime import PolicyController, PolicyRuntime
    from generalist_control.scenarios import references
    from generalist_control.simulate import Run, simulate_many
    from generalist_control.windows import Windows, history_windows, pad_states

    tags = {str(k): int(v) for k, v in meta["tags"].items()}
    if plants is None:
        known = set(available_plants())
        plants = [k for k in sorted(tags, key=tags.get) if k in known]
    plants = list(plants)
    missing = [p for p in plants if p not in tags]
    if missing:
        raise KeyError(f"the policy was not trained on {', '.join(missing)}")
    loaded = [load_plant(name) for name in plants]
    runtime = PolicyRuntime(policy, dict(meta))
    history = int(meta["history"])
    experts = int(policy.config["experts"])
    spec = {"kind": "step", "amplitude": 1.0, "duration": float(duration)}
    out: dict[str, np.ndarray] = {}
    by_dt: dict[float, list[Any]] = {}
    for p in loaded:
        by_dt.setdefault(p.dt, []).append(p)
    for group in by_dt.values():
        runs = [Run(p, *references("step", spec, p), None) for p in group]
        trajs = simulate_many(runs, PolicyController(runtime))
        for p, tr in zip(group, trajs, strict=True):
            steps = tr.r.shape[1]
            x = pad_states(tr.x[:, :steps])
            order = np.full(x.shape[0], p.order)
            state, mask, ref = history_windows(x, tr.r, order, history)
            B, N = tr.r.shape
            windows = Windows(
                state=np.ascontiguousarray(state).reshape(B * N, history, -1),
                mask=np.ascontiguousarray(mask).reshape(B * N, history, -1),
                ref=np.ascontiguousarray(ref).reshape(B * N, history),
                tag=np.full(B * N, tags[p.name], dtype=np.int64),
                target=None,
                traj=np.repeat(np.arange(B, dtype=np.int64), N),
            )
            _, gates = policy.predict_windows(windows)
            out[p.name] = gates.mean(axis=0)
    cols = [f"expert_{i + 1}" for i in range(experts)]
    df = pd.DataFrame([out[p] for p in plants], index=pd.Index(plants, name="plant"), columns=cols)
    return df.astype(float)


# --- drawing (Axes-level, reused by the notebooks) ---------------------------------------


def _fmt(v: float | None) -> str:
    """Three significant digits, as the paper writes them: ``9.43e-04``, ``0.144``, ``1.35``."""
    if v is None or not np.isfinite(v):
        return NOT_AVAILABLE
    if v != 0 and abs(v) < 0.1:
        return f"{v:.2e}"
    return f"{v:.3g}" if abs(v) < 1e4 else f"{v:,.0f}"


def draw_mse_bars(ax: Axes, mse: pd.DataFrame, sweep: str) -> Axes:
    """Grouped bars of per-plant output MSE, one bar per sweep value, log y.

    Colours follow the position of the value in the sweep (as in :func:`draw_loss_curves`).
    A value without a run is listed in the legend as "no run"; a run without a score for a
    plant shows "no score" at that bar's place.
    """
    df = mse[mse["sweep"] == sweep]
    plants = list(dict.fromkeys(df["plant"]))
    values = list(dict.fromkeys(df["value"]))
    width = 0.8 / max(1, len(values))
    x = np.arange(len(plants))
    handles = []
    for i, value in enumerate(values):
        part = df[df["value"] == value].set_index("plant").reindex(plants)
        pos = x - 0.4 + width * (i + 0.5)
        label = _label(sweep, value)
        if (part["status"] == NO_RUN).all():
            handles.append(
                Patch(facecolor="none", edgecolor=f"C{i}", hatch="//", label=f"{label} ({NO_RUN})")
            )
            continue
        handles.append(Patch(facecolor=f"C{i}", label=label))
        heights = part["mse"].to_numpy(dtype=float)
        ok = np.isfinite(heights) & (heights > 0)
        ax.bar(pos[ok], heights[ok], width, color=f"C{i}")
        for px in pos[~ok]:
            ax.text(
                px,
                0.02,
                NOT_AVAILABLE,
                ha="center",
                va="bottom",
                fontsize=7,
                rotation=90,
                color=f"C{i}",
                transform=ax.get_xaxis_transform(),
            )
    if (df["mse"] > 0).any():
        ax.set_yscale("log")
    ax.set_xticks(x, [p.replace("_", "\n") for p in plants], fontsize=8)
    ax.set_ylabel("output MSE, GC vs LQI (unit step)")
    ax.set_title(f"Closed-loop output MSE by {SWEEPS[sweep]}")
    ax.legend(handles=handles, fontsize=8)
    ax.grid(axis="y", which="both", alpha=0.3)
    return ax


def _paper_key(sweep: str, value: int, baseline: Mapping[str, int]) -> str:
    if sweep == "hidden":
        return f"d={value},M={baseline['experts']}"
    return f"d={baseline['hidden']},M={value}"


def draw_loss_curves(
    ax: Axes,
    loss: pd.DataFrame,
    sweep: str,
    values: Sequence[int] | None = None,
    paper: bool = True,
    baseline: Mapping[str, int] | None = None,
) -> Axes:
    """Training-loss curves (log y) of a sweep; the paper's final losses as dotted lines.

    Parameters
    ----------
    ax : Axes
    loss : DataFrame
        From :func:`loss_frame`.
    sweep : {"hidden", "experts"}
    values : sequence of int, optional
        The sweep's values, which fix the colours (default: the values in ``loss``); the
        paper's final loss is drawn for each, whether or not it has a run.
    paper : bool
        Draw the paper's final training losses.
    baseline : mapping, optional
        ``hidden`` and ``experts`` of the baseline (default 32 and 3).
    """
    base = {"hidden": 32, "experts": 3, **(baseline or {})}
    df = loss[loss["sweep"] == sweep]
    values = list(values) if values is not None else sorted(set(df["value"]))
    for i, value in enumerate(values):
        part = df[df["value"] == value]
        label = _label(sweep, value) + ("" if len(part) else f" ({NO_RUN})")
        ax.plot(part["epoch"], part["train_loss"], color=f"C{i}", label=label, marker=".")
        ref = ABLATION["final_train_loss"].get(_paper_key(sweep, value, base))
        if paper and ref is not None:
            ax.axhline(ref, color=f"C{i}", ls=":", lw=1)
    if paper:
        ax.plot([], [], color="grey", ls=":", label="paper, final")
    ax.set_yscale("log")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("epoch")
    ax.set_ylabel("train/loss")
    ax.set_title(f"Training loss by {SWEEPS[sweep]}")
    ax.legend(fontsize=8)
    ax.grid(which="both", alpha=0.3)
    return ax


def draw_params_vs_mse(ax: Axes, params: pd.DataFrame) -> Axes:
    """Parameter count against mean output MSE, one labelled point per run.

    A mean over fewer plants than the others (a plant without a score) is labelled with
    the count, e.g. ``d=32,M=1 (1/2 plants)``. The paper's parameter counts are dotted.
    """
    df = params.dropna(subset=["n_parameters"])
    ax.scatter(df["n_parameters"], df["mse_mean"], zorder=3)
    most = int(df["n_plants"].max()) if len(df) else 0
    for _, row in df.iterrows():
        if np.isfinite(row["mse_mean"]):
            text = row["label"]
            if row["n_plants"] < most:
                text += f" ({row['n_plants']}/{most} plants)"
            ax.annotate(
                text,
                (row["n_parameters"], row["mse_mean"]),
                fontsize=8,
                xytext=(4, 4),
                textcoords="offset points",
            )
    for key, n in ABLATION["parameters"].items():
        ax.axvline(n, color="grey", ls=":", lw=1)
        ax.text(
            n,
            0.98,
            f" paper {key}: {n:,}",
            rotation=90,
            va="top",
            fontsize=7,
            color="grey",
            transform=ax.get_xaxis_transform(),
        )
    ax.set_xscale("log")
    if (df["mse_mean"] > 0).any():
        ax.set_yscale("log")
    ax.set_xlabel("parameters")
    ax.set_ylabel("mean output MSE")
    ax.set_title("Complexity against performance")
    ax.grid(which="both", alpha=0.3)
    return ax


def draw_gate_heatmap(ax: Axes, gates: pd.DataFrame) -> Axes:
    """Mean gate weight per plant (rows) and expert (columns), annotated in percent."""
    im = ax.imshow(gates.to_numpy(), vmin=0.0, vmax=1.0, cmap="viridis", aspect="auto")
    for (i, j), v in np.ndenumerate(gates.to_numpy()):
        ax.text(
            j,
            i,
            f"{100 * v:.0f}%",
            ha="center",
            va="center",
            fontsize=7,
            color="white" if v < 0.6 else "black",
        )
    ax.set_xticks(range(gates.shape[1]), [c.replace("expert_", "E") for c in gates.columns])
    ax.set_yticks(range(gates.shape[0]), list(gates.index), fontsize=7)
    ax.set_xlabel("expert")
    ax.set_title("Mean gate weight")
    ax.figure.colorbar(im, ax=ax, fraction=0.046)
    return ax


def _figure(width: float, height: float, ncols: int = 1) -> tuple[Figure, list[Axes]]:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)  # the Agg backend, without touching pyplot's global state
    return fig, list(np.atleast_1d(fig.subplots(1, ncols)))


def _placeholder(ax: Axes, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", wrap=True, transform=ax.transAxes)
    ax.set_axis_off()


# --- the comparison with the paper --------------------------------------------------------


def _parse_key(key: str) -> tuple[int, int]:
    m = re.fullmatch(r"d=(\d+),M=(\d+)", key)
    if not m:
        raise ValueError(f"unexpected configuration key '{key}'")
    return int(m.group(1)), int(m.group(2))


def comparison_markdown(
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    mse: pd.DataFrame,
    gates: pd.DataFrame | None,
    gate_run: RunPoint | None,
    eval_summary: Mapping[str, Any] | None = None,
) -> str:
    """Markdown: our ablation figures beside the paper's, and the per-plant MSE tables."""
    by_cfg = {(p.hidden, p.experts): p for p in _unique_points(sweeps)}

    def find(key: str) -> RunPoint | None:
        return by_cfg.get(_parse_key(key))

    def mse_of(p: RunPoint | None, plant: str) -> str:
        if p is None:
            return NO_RUN
        return _fmt(p.mse.get(plant))

    def run_of(p: RunPoint | None) -> str:
        return f"`{p.run_id[:8]}`" if p else ""

    lines = [
        "# Ablation study (Section 7): our runs beside the paper",
        "",
        "Redrawn from the MLflow training runs by `python -m generalist_control.report`. "
        '"no run": no finished run of that configuration; "no score": the run has no score '
        "(diverged, or not trained on the plant). Our training loss is the MSE on normalised "
        "controls (see docs/training.md); MSE is GC against LQI, unit step, ablation set.",
        "",
        "| quantity | configuration | paper | ours | run |",
        "| --- | --- | --- | --- | --- |",
    ]
    for key, ref in ABLATION["final_train_loss"].items():
        p = find(key)
        ours = NO_RUN if p is None else _fmt(p.train_loss)
        lines.append(f"| final training loss | {key} | {_fmt(ref)} | {ours} | {run_of(p)} |")
    for key, ref in ABLATION["parameters"].items():
        p = find(key)
        ours = (
            NO_RUN if p is None else (f"{p.n_parameters:,}" if p.n_parameters else NOT_AVAILABLE)
        )
        approx = "" if key == "d=32,M=3" else "≈"
        lines.append(f"| parameters | {key} | {approx}{ref:,} | {ours} | {run_of(p)} |")
    for name, plant in (("crazyflie_mse", "crazyflie_altitude"), ("hvac_mse", "hvac_two_zone")):
        for key, ref in ABLATION[name].items():
            p = find(key)
            lines.append(
                f"| {plant} MSE | {key} | {_fmt(ref)} | {mse_of(p, plant)} | {run_of(p)} |"
            )
    gate_cfg = gate_run.label if gate_run else "d=32,M=5"  # the paper's gate model
    for plant, ref in ABLATION["gate_weights_m5"].items():
        ((expert, weight),) = ref.items()
        paper = f"{expert.replace('_', ' ')}: {weight:.0%}"
        if gates is None or gate_run is None:
            ours = NO_RUN
        elif plant not in gates.index:
            ours = "not trained on it"
        else:
            row = gates.loc[plant]
            ours = f"{row.idxmax().replace('_', ' ')}: {row.max():.0%} (dominant)"
        lines.append(
            f"| gate weight, {plant} | {gate_cfg} | {paper} | {ours} | {run_of(gate_run)} |"
        )
    lines += [
        "",
        "Expert numbering is arbitrary (any permutation of the experts is the same model), so "
        "for the gate weights compare the dominant expert's share, not its index.",
    ]
    for sweep, symbol in SWEEPS.items():
        part = mse[mse["sweep"] == sweep]
        if part.empty:
            continue
        values = list(dict.fromkeys(part["value"]))
        lines += [
            "",
            f"## Output MSE by {symbol} (figure `mse_{sweep}.png`)",
            "",
            "| plant | " + " | ".join(_label(sweep, v) for v in values) + " |",
            "| --- |" + " --- |" * len(values),
        ]
        for plant, rows in part.groupby("plant", sort=False):
            cells = []
            for v in values:
                r = rows[rows["value"] == v].iloc[0]
                cells.append(_fmt(r["mse"]) if r["status"] == "ok" else r["status"])
            lines.append(f"| {plant} | " + " | ".join(cells) + " |")
    if eval_summary:
        qb = eval_summary.get("quality_bar", {})
        lines += [
            "",
            "## The pipeline's model (evaluate stage, reports/eval/summary.json)",
            "",
            "| quality bar | met |",
            "| --- | --- |",
            *[f"| {k} | {v} |" for k, v in qb.items()],
        ]
    return "\n".join(lines) + "\n"


# --- the report ---------------------------------------------------------------------------


def _publish(staging: Path, out_dir: Path) -> None:
    old = out_dir.with_name(f".{out_dir.name}.old-{os.getpid()}")
    if out_dir.exists():
        os.replace(out_dir, old)
    os.replace(staging, out_dir)
    shutil.rmtree(old, ignore_errors=True)


def _finite(value: Any) -> float | None:
    """A finite float, or None (for JSON)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def runs_table(sweeps: Mapping[str, Mapping[int, RunPoint | None]]) -> pd.DataFrame:
    """One row per sweep point: its run (or "no run") and the run's figures."""
    rows = []
    for sweep, by_value in sweeps.items():
        for value, p in by_value.items():
            rows.append(
                {
                    "sweep": sweep,
                    "value": value,
                    "label": _label(sweep, value),
                    "status": "ok" if p else NO_RUN,
                    "run_id": p.run_id if p else None,
                    "run_name": p.run_name if p else None,
                    "hidden": p.hidden if p else None,
                    "experts": p.experts if p else None,
                    "n_parameters": p.n_parameters if p else None,
                    "final_train_loss": p.train_loss if p else None,
                    "closed_loop_diverged": p.diverged if p else None,
                }
            )
    return pd.DataFrame(rows)


def write_report(
    out_dir: str | Path,
    sweeps: Mapping[str, Mapping[int, RunPoint | None]],
    plants: Sequence[str],
    client: Any | None = None,
    gate: Mapping[str, Any] | None = None,
    baseline: Mapping[str, int] | None = None,
    eval_summary: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Draw every figure and table from the selected runs; write them atomically.

    Parameters
    ----------
    out_dir : path
        Replaced as a whole (staged in a temporary sibling directory, then renamed).
    sweeps : mapping
        From :func:`select_sweeps`.
    plants : sequence of str
        Plants of the MSE figures (``closed_loop/mse/<plant>``).
    client : mlflow.tracking.MlflowClient, optional
    gate : mapping, optional
        ``experts`` (M of the gate-weight model, default 5), ``plants`` (None: all it
        knows), ``duration`` (s).
    baseline : mapping, optional
        ``hidden`` of the gate-weight model (default 32).
    eval_summary : mapping, optional
        The evaluate stage's ``summary.json``, quoted in ``comparison.md``.

    Returns
    -------
    dict
        The summary also written to ``summary.json``: run ids per point, missing points,
        the gate model's run.
    """
    client = client or _client()
    gate = dict(gate or {})
    base = {"hidden": 32, "experts": 3, **(baseline or {})}
    gate_m = int(gate.get("experts", 5))
    sweeps = {k: dict(v) for k, v in sweeps.items()}
    mse = mse_frame(sweeps, plants)
    loss = loss_frame(sweeps, client)
    params = params_frame(sweeps, plants)
    gate_run = sweeps.get("experts", {}).get(gate_m)
    if gate_run is None:
        gate_run = next(
            (
                p
                for p in _unique_points(sweeps)
                if (p.hidden, p.experts) == (base["hidden"], gate_m)
            ),
            None,
        )
    gates = None
    if gate_run is not None:
        policy, meta = policy_of_run(gate_run.run_id, client)
        gates = gate_weights(policy, meta, gate.get("plants"), float(gate.get("duration", 15.0)))

    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        for sweep in SWEEPS:
            mse[mse["sweep"] == sweep].to_csv(staging / f"mse_{sweep}.csv", index=False)
            loss[loss["sweep"] == sweep].to_csv(staging / f"loss_{sweep}.csv", index=False)
            fig, (ax,) = _figure(7, 4)
            draw_mse_bars(ax, mse, sweep)
            fig.savefig(staging / f"mse_{sweep}.png", dpi=120)
            fig, (ax,) = _figure(6, 4)
            draw_loss_curves(ax, loss, sweep, list(sweeps.get(sweep, {})), baseline=base)
            fig.savefig(staging / f"loss_{sweep}.png", dpi=120)
        params.to_csv(staging / "params_vs_mse.csv", index=False)
        fig, (ax,) = _figure(6, 4)
        draw_params_vs_mse(ax, params)
        fig.savefig(staging / "params_vs_mse.png", dpi=120)

        gate_csv = staging / "gate_weights.csv"
        fig, (ax,) = _figure(6, max(2.5, 0.8 + 0.3 * (len(gates) if gates is not None else 0)))
        if gates is not None:
            gates.to_csv(gate_csv)
            draw_gate_heatmap(ax, gates)
            ax.set_title(f"Mean gate weight, {gate_run.label} (run {gate_run.run_id[:8]})")
        else:
            cols = ["plant", *[f"expert_{i + 1}" for i in range(gate_m)]]
            pd.DataFrame(columns=cols).to_csv(gate_csv, index=False)
            _placeholder(ax, f"{NO_RUN}: no finished run with d={base['hidden']}, M={gate_m}")
        fig.savefig(staging / "gate_weights.png", dpi=120)

        fig, axes = _figure(13, 4, ncols=2)  # the paper's Fig. hidden_ablation
        draw_mse_bars(axes[0], mse, "hidden")
        draw_loss_curves(axes[1], loss, "hidden", list(sweeps.get("hidden", {})), baseline=base)
        fig.savefig(staging / "fig_hidden_ablation.png", dpi=120)
        fig, axes = _figure(13, 4, ncols=2)  # the paper's Fig. expert_ablation
        draw_mse_bars(axes[0], mse, "experts")
        expert_ids = {p.run_id for p in sweeps.get("experts", {}).values() if p}
        draw_params_vs_mse(axes[1], params[params["run_id"].isin(expert_ids)])
        fig.savefig(staging / "fig_expert_ablation.png", dpi=120)

        runs_table(sweeps).to_csv(staging / "runs.csv", index=False)
        text = comparison_markdown(sweeps, mse, gates, gate_run, eval_summary)
        (staging / "comparison.md").write_text(text)
        summary = {
            "points": {
                sweep: {_label(sweep, v): (p.run_id if p else None) for v, p in by_v.items()}
                for sweep, by_v in sweeps.items()
            },
            "missing": [
                _label(sweep, v)
                for sweep, by_v in sweeps.items()
                for v, p in by_v.items()
                if p is None
            ],
            "gate_run": gate_run.run_id if gate_run else None,
            "plants": list(plants),
            "configs": {
                row.label: {
                    "run_id": row.run_id,
                    "final_train_loss": _finite(row.final_train_loss),
                    "n_parameters": _finite(row.n_parameters),
                    "mse_mean": _finite(row.mse_mean),
                }
                for row in params.itertuples()
            },
        }
        (staging / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        os.chmod(staging, 0o755)
        _publish(staging, out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return summary


def _log_to_mlflow(
    cfg: DictConfig, experiment: str, out_dir: Path, summary: Mapping[str, Any]
) -> str:
    """Log the report as a ``report`` run of the experiment; return its run id."""
    import mlflow

    from generalist_control import mlflow_utils

    rcfg = cfg.report
    logger = {
        **OmegaConf.to_container(cfg.logger, resolve=True),
        "experiment_name": experiment,
        "run_name": rcfg.get("run_name") or "ablation-report",
    }
    with mlflow_utils.mlflow_run(logger) as active:
        mlflow.set_tags(
            {
                RUN_TYPE_TAG: "report",
                "report.kind": "ablation",
                "report.missing": ", ".join(summary["missing"]) or "none",
            }
        )
        flat = mlflow_utils.flatten_params({"report": OmegaConf.to_container(rcfg, resolve=True)})
        mlflow.log_params(flat)
        mlflow.log_dict(dict(summary), "ablation/summary.json")
        mlflow.log_artifacts(str(out_dir), "ablation")
        metrics = {"report/missing_points": float(len(summary["missing"]))}
        for label, fig in summary["configs"].items():
            key = label.replace("=", "").replace(",", "_")  # d32_M3
            for name in ("final_train_loss", "n_parameters", "mse_mean"):
                value = fig.get(name)
                if value is not None and np.isfinite(value):
                    metrics[f"ablation/{name}/{key}"] = float(value)
        mlflow.log_metrics(metrics)
        return active.info.run_id


def run(cfg: DictConfig) -> dict[str, Any]:
    """Find the sweep runs, write ``report.out_dir`` and log the report to MLflow.

    Training runs that lie on neither sweep (e.g. a ``dvc exp run -S experts=4``) leave
    every point "no run" in the report, with a warning naming the sweep commands.

    Raises
    ------
    NoAblationRunsError
        If the experiment holds no finished training run at all; nothing is written.
    """
    from generalist_control import mlflow_utils

    if cfg.get("threads"):
        import torch

        torch.set_num_threads(int(cfg.threads))
    rcfg = cfg.report
    experiment = rcfg.get("experiment_name") or cfg.logger.experiment_name
    uri = mlflow_utils.set_tracking(cfg.logger)
    client = _client(uri)
    points = runs_from_mlflow(experiment, rcfg.get("filter_string") or "", client)
    baseline = OmegaConf.to_container(rcfg.baseline, resolve=True)
    sweeps = select_sweeps(points, list(rcfg.hidden), list(rcfg.experts), baseline)
    if not points:
        raise NoAblationRunsError(
            f"no finished training run in MLflow experiment '{experiment}' at {uri} "
            f"(filter: {rcfg.get('filter_string')!r}). Create the ablation runs with:\n  "
            + "\n  ".join(SWEEP_COMMANDS)
        )
    plants = rcfg.get("plants")
    if plants is None:
        plants = (cfg.get("closed_loop") or {}).get("systems")
    plants = list(plants or [])
    if not plants:
        plants = sorted({k for p in _unique_points(sweeps) for k in p.mse})
    eval_summary = None
    summary_path = Path(cfg.paths.get("reports_dir", "reports/eval")) / "summary.json"
    if summary_path.is_file():
        eval_summary = json.loads(summary_path.read_text())
    out_dir = Path(rcfg.out_dir)
    gate = OmegaConf.to_container(rcfg.gate, resolve=True) if rcfg.get("gate") else {}
    summary = write_report(out_dir, sweeps, plants, client, gate, baseline, eval_summary)
    if summary["missing"]:
        log.warning(
            "no run for %s; create them with: %s",
            ", ".join(summary["missing"]),
            " and ".join(SWEEP_COMMANDS),
        )
    if rcfg.get("log_mlflow", True):
        summary["report_run_id"] = _log_to_mlflow(cfg, experiment, out_dir, summary)
    log.info("ablation report written to %s", out_dir)
    return summary


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``report`` stage."""
    run(cfg)


if __name__ == "__main__":
    main()
