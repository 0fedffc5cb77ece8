"""One MLflow experiment per kind of work, so that budgets and studies never mix by default.

The scheme, ``<logger.experiment_prefix>/<kind>``, and what each kind holds: docs/sweeps.md.
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

#: MLflow 3's experiment type tag and its value for model training (not GenAI).
KIND_TAG = ("mlflow.experimentKind", "custom_model_development")


def experiment_name(logger: Mapping[str, Any], kind: str) -> str:
    """``logger.experiment_name`` if set, else ``<logger.experiment_prefix>/<kind>``.

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
