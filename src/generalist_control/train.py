"""The ``train`` stage: ``python train.py`` at the repo root, ``gc-train``, ``dvc repro train``.

The config is read once (:func:`~.training.settings.read_training`); the work is
:func:`~.training.fit.train`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from omegaconf import DictConfig

from generalist_control.common.sections import as_dict
from generalist_control.common.stage_main import stage_main
from generalist_control.training.settings import read_training

__all__ = ["main", "run"]


def run(cfg: DictConfig) -> dict[str, Any]:
    """Train the policy ``cfg`` describes; return its metrics."""
    settings = read_training(as_dict(cfg))
    # Lightning and MLflow load once the config is read: ``--help`` and a refused config
    # answer in a second or two, not after their imports.
    from generalist_control.training.fit import train

    metrics, _ = train(settings)
    return metrics


@stage_main("config")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: train and return the optimised metric (``optimized_metric``)."""
    metrics = run(cfg)
    return float(metrics.get(str(cfg.optimized_metric), np.nan))


if __name__ == "__main__":
    main()
