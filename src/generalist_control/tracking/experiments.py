"""One MLflow experiment per kind of work, so that budgets and studies never mix by default.

Naming scheme: ``<logger.experiment_prefix>/<kind>`` (prefix ``generalist-control``):

=============  ===========================================================================
kind           written by
=============  ===========================================================================
``train``      a single ``python train.py`` and the DVC stage ``train``
``sweep``      ``python train.py -m ...`` (a parent run per sweep, its jobs nested under it)
``tune``       ``python tune.py`` (a parent run per Optuna study, its trials nested)
``report``     ``python -m generalist_control.report`` (the ablation report's own run)
``ablation``   the DVC ablation pipeline (``ablation/dvc.yaml``)
``tag-free``   the DVC stage ``tag_free``
``variants``   the DVC stage ``variants``
``adapt``      ``python -m generalist_control.adapt`` (a plant added to a trained policy)
``unseen``     the DVC stage ``unseen``'s trainings without the held-out plants
``evaluate``   an evaluation of a policy whose training run this store does not hold
=============  ===========================================================================

An explicit ``logger.experiment_name`` overrides the scheme (every run then lands there).
Every experiment is tagged as model development (:data:`KIND_TAG`), so that ``mlflow ui``
opens it on its runs, not on MLflow's GenAI overview.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["DEFAULT_PREFIX", "KINDS", "KIND_TAG", "experiment_name"]

DEFAULT_PREFIX = "generalist-control"

#: The kinds of work, each with its own experiment.
KINDS = (
    "train", "sweep", "tune", "report", "ablation", "tag-free", "variants", "adapt", "unseen",
    "evaluate",
)  # fmt: skip

#: MLflow 3's experiment type tag and its value for model training (not GenAI), as its UI
#: sets it when a user picks the experiment's type.
KIND_TAG = ("mlflow.experimentKind", "custom_model_development")


def experiment_name(logger: Mapping[str, Any], kind: str) -> str:
    """The MLflow experiment a run of ``kind`` goes to.

    Parameters
    ----------
    logger : mapping
        The ``logger`` config: ``experiment_name`` (explicit, wins when set) and
        ``experiment_prefix`` (default ``generalist-control``).
    kind : str
        One of :data:`KINDS`.

    Returns
    -------
    str
        ``logger.experiment_name`` if set, else ``<experiment_prefix>/<kind>``.

    Raises
    ------
    ValueError
        If ``kind`` is not one of :data:`KINDS`.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown kind of work {kind!r}; expected one of {', '.join(KINDS)}")
    explicit = logger.get("experiment_name")
    if explicit:
        return str(explicit)
    prefix = str(logger.get("experiment_prefix") or DEFAULT_PREFIX)
    return f"{prefix}/{kind}"
