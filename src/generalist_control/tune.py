"""Optuna search of the training's hyper-parameters: ``python tune.py [overrides]`` (``gc-tune``).

The search section is read here, once; the rest of the config is each trial's training's.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import optuna
from omegaconf import DictConfig, OmegaConf, open_dict
from optuna.trial import TrialState

from generalist_control.common.paths import stage_dir
from generalist_control.common.sections import as_dict, read_section
from generalist_control.common.stage_main import stage_main
from generalist_control.common.stop_signals import exiting_on_signals
from generalist_control.sweeps.search_settings import SearchSettings, fixed_config, parse_space
from generalist_control.training.settings import read_training

__all__ = ["main", "run", "trial_config"]


def trial_config(
    cfg: DictConfig, values: Mapping[str, Any], trial_dir: Path, monitor: str, experiment: str
) -> DictConfig:
    """The training config of one trial: ``cfg`` with ``values`` set, outputs in ``trial_dir``.

    The run goes to the study's ``experiment``; the callbacks get the trial's pruning (on
    ``monitor``) and its link to the run.
    """
    from generalist_control.sweeps.trial_callbacks import TrialRunLink, trial_pruning

    tcfg = copy.deepcopy(cfg)
    with open_dict(tcfg):
        tcfg.pop("hparams_search", None)
        for key, value in values.items():
            OmegaConf.update(tcfg, key, value, merge=False)
        tcfg.run_dir = str(trial_dir / "run")
        tcfg.paths.models_dir = str(trial_dir / "models")
        tcfg.logger.experiment_name = experiment
        if tcfg.get("callbacks") is None:
            tcfg.callbacks = {}
        tcfg.callbacks.optuna_pruning = {
            "_target_": f"{trial_pruning.__module__}.{trial_pruning.__name__}",
            "monitor": monitor,
        }
        tcfg.callbacks.optuna_run_link = {
            "_target_": f"{TrialRunLink.__module__}.{TrialRunLink.__name__}",
        }
    return tcfg


def run(cfg: DictConfig) -> optuna.Study:
    """Run (or continue) the study that ``cfg.hparams_search`` configures; return it.

    The settings and the search space are checked before the storage or MLflow is touched.
    """
    if cfg.get("hparams_search") is None:
        raise ValueError("no search configured: choose one, e.g. hparams_search=default")
    search = read_section(SearchSettings, as_dict(cfg.hparams_search), "hparams_search")
    space = parse_space(search.params, cast(dict, OmegaConf.to_container(cfg, resolve=False)))
    tree = {k: v for k, v in as_dict(cfg).items() if k != "hparams_search"}
    fixed = fixed_config(tree, search.metric, [p.key for p in space], search.identity_keys)
    # Lightning loads once the search is read: ``--help`` and a refused search answer without it
    from generalist_control.sweeps.study import run_study, tune_logger
    from generalist_control.training.fit import train

    logger = tune_logger(as_dict(cfg.logger))

    def train_point(values: Mapping[str, Any], trial_dir: Path) -> Mapping[str, Any]:
        experiment = logger["experiment_name"]
        tcfg = trial_config(cfg, values, trial_dir, search.monitor, experiment)
        return train(read_training(as_dict(tcfg)))[0]

    # trials_dir, else <Hydra output dir or outputs/tune/<time>>/<study_name>
    trials_dir = Path(search.trials_dir or stage_dir("tune") / search.study_name)
    return run_study(search, space, fixed, logger, train_point, trials_dir)


@stage_main("tune")
def _main(cfg: DictConfig) -> float:
    """Hydra entry point: run the study; return its best value (NaN if none completed)."""
    study = run(cfg)
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    return float(study.best_value) if complete else math.nan


def main() -> None:
    """``python tune.py``: exit 128 + the signal's number when SIGTERM or SIGINT stops it."""
    with exiting_on_signals("the running trial failed, the study's run ended KILLED"):
        _main()


if __name__ == "__main__":
    main()
