"""Synthetic ablation runs in MLflow, logged as ``train.py`` logs them (report tests)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import mlflow

from generalist_control.model.network import count_parameters
from generalist_control.model.policy import Policy, save_policy
from generalist_control.plants.catalog import load_plant
from helpers import net_config

PLANTS = ("double_integrator", "cstr")
#: (d, M) -> (final train loss, {plant: mse}); d = 16 is left out on purpose.
CONFIGS = {
    (32, 3): (9e-4, {"double_integrator": 1e-3, "cstr": 2e-3}),
    (64, 3): (4e-4, {"double_integrator": 5e-4, "cstr": 1e-3}),
    (32, 1): (3e-3, {"double_integrator": 1e-2}),  # cstr "diverged": no score logged
    (32, 5): (6e-4, {"double_integrator": 8e-4, "cstr": 9e-4}),
}


def policy_meta() -> dict:
    plants = [load_plant(name) for name in PLANTS]
    return {
        "tags": {p.name: p.tag for p in plants},
        "orders": {p.name: p.order for p in plants},
        "dt": 0.05,
        "history": 8,
        "horizon": 3,
    }


def experiment(uri: str, name: str, tmp: Path) -> str:
    """The id of the experiment ``name`` in ``uri``, created if missing."""
    mlflow.set_tracking_uri(uri)
    found = mlflow.get_experiment_by_name(name)
    if found:
        return found.experiment_id
    return mlflow.create_experiment(name, artifact_location=(tmp / "art").as_uri())


def log_run(
    exp_id: str,
    tmp: Path,
    d: int,
    m: int,
    loss: float,
    mse: Mapping[str, float],
    params: Mapping[str, Any] | None = None,
    parent: str | None = None,
    tags: Mapping[str, str] | None = None,
) -> str:
    """One finished training-like run of (d, M); its id. A policy artifact when M = 5.

    ``loss`` is the final ``train/loss`` (the history ends with it), ``mse`` the
    ``closed_loop/mse/<plant>`` scores, ``params`` further params (``seed``, ...), ``tags``
    further tags (``policy_dir``, ...).
    """
    policy = Policy(net_config(hidden=d, experts=m, heads=2))
    tags = {**(tags or {}), **({"mlflow.parentRunId": parent} if parent else {})}
    with mlflow.start_run(experiment_id=exp_id, run_name=f"d{d}-M{m}", tags=tags) as r:
        mlflow.log_params(
            {"model.hidden": d, "experts": m, "n_parameters": count_parameters(policy)}
        )
        mlflow.log_params({k: str(v) for k, v in (params or {}).items()})
        for epoch, factor in enumerate((4.0, 2.0, 1.0)):
            mlflow.log_metric("train/loss", loss * factor, step=epoch)
            mlflow.log_metric("val/loss", 1.5 * loss * factor, step=epoch)
        mlflow.log_metrics({f"closed_loop/mse/{k}": v for k, v in mse.items()})
        mlflow.log_metric("closed_loop/diverged", float(len(PLANTS) - len(mse)))
        if m == 5:
            path = save_policy(tmp / "policy" / "policy.ckpt", policy, policy_meta())
            mlflow.log_artifact(str(path), "policy")
        return r.info.run_id


def log_runs(
    uri: str,
    experiment_name: str,
    tmp: Path,
    params: Mapping[tuple[int, int], Mapping[str, Any]] | None = None,
    parent: str | None = None,
    configs: Mapping[tuple[int, int], Any] | None = None,
) -> dict[tuple[int, int], str]:
    """One finished training-like run per configuration, as train.py logs them.

    ``params``: further params per configuration (e.g. ``trainer.max_epochs``); ``parent``:
    the parent run (a sweep) the runs are nested under; ``configs``: a subset of CONFIGS.
    The experiment is created if missing.
    """
    exp_id = experiment(uri, experiment_name, tmp)
    return {
        (d, m): log_run(exp_id, tmp, d, m, loss, mse, (params or {}).get((d, m)), parent)
        for (d, m), (loss, mse) in (configs or CONFIGS).items()
    }
