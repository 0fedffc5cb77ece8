"""Optuna search of the training's hyper-parameters: ``python tune.py [overrides]``.

Also ``gc-tune`` and ``python -m generalist_control.tune``; the study itself is
:mod:`generalist_control.sweeps.study` (docs/sweeps.md).
"""

from __future__ import annotations

import math

import hydra
import optuna
from omegaconf import DictConfig
from optuna.trial import TrialState

from generalist_control.common.paths import HYDRA_CONFIG_PATH
from generalist_control.sweeps import study as _study

__all__ = ["main", "run"]


def run(cfg: DictConfig) -> optuna.Study:
    """Run (or continue) the configured study; see :func:`generalist_control.sweeps.study.run`."""
    return _study.run(cfg)


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="tune")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: run the study; return its best value (NaN if none completed)."""
    study = run(cfg)
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    return float(study.best_value) if complete else math.nan


if __name__ == "__main__":
    main()
