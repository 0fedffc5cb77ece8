"""The ``report`` stage: ``python -m generalist_control.report`` or ``dvc repro report``.

The ablation figures of the paper's Section 7, redrawn from the finished training runs in
MLflow (:mod:`generalist_control.reports.ablation`); settings in ``conf/report``.
"""

from __future__ import annotations

from typing import Any

import hydra
from omegaconf import DictConfig

from generalist_control.common.paths import HYDRA_CONFIG_PATH
from generalist_control.reports.ablation import build_report

__all__ = ["main", "run"]


def run(cfg: DictConfig) -> dict[str, Any]:
    """Find the sweep runs, write ``report.out_dir`` and log the report to MLflow."""
    return build_report(cfg)


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``report`` stage."""
    run(cfg)


if __name__ == "__main__":
    main()
