"""The ablation's training runs, read back from MLflow: one :class:`RunPoint` per run."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import mlflow

from generalist_control.evaluation.eval_run import RUN_TYPE_TAG
from generalist_control.tracking.parents import ROLE_TAG

__all__ = [
    "ByConfig",
    "NOT_AVAILABLE",
    "NO_RUN",
    "SWEEPS",
    "SWEEP_COMMANDS",
    "Sweeps",
    "NoAblationRunsError",
    "RunPoint",
    "infer_recipe",
    "point_label",
    "run_label",
    "runs_from_mlflow",
    "seed_runs",
    "select_sweeps",
    "unique_points",
]

log = logging.getLogger(__name__)

#: The commands that create the sweep runs (quoted when there are none).
SWEEP_COMMANDS = (
    "python train.py -m model.hidden=16,32,64",
    "python train.py -m experts=1,3,5",
)
#: Sweep name (the run attribute) -> the symbol used in labels.
SWEEPS = {"hidden": "d", "experts": "M"}
NO_RUN = "no run"
NOT_AVAILABLE = "no score"


class NoAblationRunsError(LookupError):
    """The MLflow experiment holds no finished training run to report on."""


@dataclass(frozen=True)
class RunPoint:
    """The figures of one finished training run that the report needs (its last logged)."""

    run_id: str
    run_name: str
    hidden: int  #: ``model.hidden`` (d)
    experts: int  #: ``experts`` (M)
    n_parameters: int | None
    train_loss: float | None
    mse: dict[str, float] = field(default_factory=dict)  #: ``closed_loop/mse/<plant>``
    diverged: int = 0  #: ``closed_loop/diverged``: plants whose GC loop diverged
    start_time: int = 0  #: ms since the epoch
    params: Mapping[str, str] = field(default_factory=dict, compare=False, repr=False)
    val_loss: float | None = None
    best_val_loss: float | None = None
    seed: int | None = None
    policy_dir: str | None = None  #: the absolute folder of its policy (tag ``policy_dir``)

    @property
    def label(self) -> str:
        """``d=<hidden>,M=<experts>``, the key format of :data:`paper.ABLATION`."""
        return f"d={self.hidden},M={self.experts}"


#: Per sweep (``hidden``, ``experts``), each swept value's run (None: no run of that point).
Sweeps = Mapping[str, Mapping[int, RunPoint | None]]
#: Per configuration (d, M), its runs, one per seed.
ByConfig = Mapping[tuple[int, int], Sequence[RunPoint]]


def _as_int(text: str | None) -> int | None:
    try:
        return int(float(text)) if text is not None else None
    except ValueError:
        return None


def _float(value: Any) -> float | None:
    return None if value is None else float(value)


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
    loss, val, best = (_float(metrics.get(k)) for k in ("train/loss", "val/loss", "best/val/loss"))
    return RunPoint(
        run_id=run.info.run_id,
        run_name=run.info.run_name or "",
        hidden=hidden,
        experts=experts,
        n_parameters=n_params,
        train_loss=loss,
        mse=mse,
        diverged=int(metrics.get("closed_loop/diverged", 0) or 0),
        start_time=int(run.info.start_time or 0),
        params=dict(params),
        val_loss=val,
        best_val_loss=best,
        seed=_as_int(params.get("seed")),
        policy_dir=tags.get("policy_dir"),
    )


def _parent_role(client: Any, roles: dict[str, str | None], run: Any) -> str | None:
    """The ``gc.role`` tag of a run's parent (None: no parent, or a deleted one), cached."""
    parent = run.data.tags.get("mlflow.parentRunId")
    if parent and parent not in roles:
        try:
            roles[parent] = client.get_run(parent).data.tags.get(ROLE_TAG)
        except Exception:  # noqa: BLE001 (a deleted parent: keep the run)
            roles[parent] = None
    return roles.get(parent) if parent else None


def runs_from_mlflow(
    experiment_name: str,
    filter_string: str = "",
    client: Any | None = None,
    parents: Sequence[str] | None = None,
) -> list[RunPoint]:
    """The training runs of an MLflow experiment (none if unknown) passing an MLflow filter.

    Report runs, parent runs and (unless ``parents`` names their study) Optuna trials are left
    out; ``parents``: keep only their children. ``client``: default, the current store's.
    """
    client = client or mlflow.MlflowClient()
    experiment = client.get_experiment_by_name(experiment_name)
    if experiment is None:
        return []
    points, token = [], None
    roles: dict[str, str | None] = {}  # parent run id -> its gc.role tag
    while True:
        page = client.search_runs(
            [experiment.experiment_id],
            filter_string=filter_string or "",
            order_by=["attributes.start_time DESC"],
            max_results=1000,
            page_token=token,
        )
        for run in page:
            if run.data.tags.get(ROLE_TAG):
                continue  # a sweep/study parent
            if parents is not None:
                if run.data.tags.get("mlflow.parentRunId") not in parents:
                    continue
            elif _parent_role(client, roles, run) == "study":
                continue  # a trial of an Optuna study
            point = _point(run)
            if point is not None:
                points.append(point)
        token = page.token
        if not token:
            break
    return sorted(points, key=lambda p: -p.start_time)


def select_sweeps(
    points: Sequence[RunPoint],
    hidden: Sequence[int],
    experts: Sequence[int],
    baseline: tuple[int, int],
) -> dict[str, dict[int, RunPoint | None]]:
    """``{"hidden": {d: run}, "experts": {M: run}}``: each point's newest run of its smallest seed.

    ``hidden`` are the values of d at the baseline's M, ``experts`` those of M at its d; a
    point without a run maps to None.
    """
    base_d, base_m = baseline
    order = sorted(points, key=lambda p: (p.seed is None, p.seed or 0, -p.start_time))

    def first(d: int, m: int) -> RunPoint | None:
        return next((p for p in order if p.hidden == d and p.experts == m), None)

    return {
        "hidden": {int(d): first(int(d), base_m) for d in hidden},
        "experts": {int(m): first(base_d, int(m)) for m in experts},
    }


def unique_points(sweeps: Sweeps) -> list[RunPoint]:
    """The runs of all sweeps, each once (the baseline belongs to both sweeps), by (d, M)."""
    seen: dict[str, RunPoint] = {}
    for by_value in sweeps.values():
        for p in by_value.values():
            if p is not None:
                seen.setdefault(p.run_id, p)
    return sorted(seen.values(), key=lambda p: (p.hidden, p.experts))


def point_label(sweep: str, value: int) -> str:
    """``d=32`` or ``M=5``: a sweep point as the figures label it."""
    return f"{SWEEPS[sweep]}={value}"


def run_label(p: RunPoint) -> str:
    """``d32-M3-s42``: a run as the tables name it (its point and its seed)."""
    return f"d{p.hidden}-M{p.experts}" + (f"-s{p.seed}" if p.seed is not None else "")


def seed_runs(points: Sequence[RunPoint], sweeps: Sweeps) -> dict[tuple[int, int], list[RunPoint]]:
    """Per configuration (d, M) of the sweeps, its newest run of each seed, by seed.

    A configuration drawn from a run that ``points`` lacks keeps that run.
    """
    out: dict[tuple[int, int], list[RunPoint]] = {}
    for drawn in unique_points(sweeps):
        config = (drawn.hidden, drawn.experts)
        by_seed: dict[int | None, RunPoint] = {}
        for p in sorted(points, key=lambda p: -p.start_time):
            if (p.hidden, p.experts) == config:
                by_seed.setdefault(p.seed, p)
        by_seed.setdefault(drawn.seed, drawn)
        out[config] = sorted(by_seed.values(), key=lambda p: (p.seed is None, p.seed or 0))
    return out


def infer_recipe(runs: Sequence[RunPoint]) -> str:
    """The runs' recipe: ``paper`` if none scales windows or runs DAgger, else ``default``."""
    if runs and all(
        str(p.params.get("model.window_scale", "")).lower() == "false"
        and not any(k.startswith("dagger.") for k in p.params)
        for p in runs
    ):
        return "paper"
    return "default"
