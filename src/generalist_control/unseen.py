"""The held-out protocol's last step: ``python -m generalist_control.unseen``.

Run by the DVC stage ``unseen`` (``beyond/dvc.yaml``) after its two trainings without the
plants of ``held_out`` (``conf/unseen.yaml``): per held-out plant, a row learned on the
default (``adapt``), the tag-free policy zero-shot and the pipeline's policy trained with it,
each on every scenario against the plant's LQI; ``reports/unseen/``. The work is
:func:`generalist_control.reports.held_out.run_unseen` (``docs/pipeline.md``).
"""

from __future__ import annotations

from typing import Any

import hydra
from omegaconf import DictConfig

from generalist_control.common.paths import HYDRA_CONFIG_PATH
from generalist_control.reports.held_out import run_unseen

__all__ = ["main", "run"]


def run(cfg: DictConfig) -> dict[str, Any]:
    """Adapt to and evaluate on every held-out plant; return the summary."""
    return run_unseen(cfg)


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="unseen")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the held-out protocol's evaluation."""
    run(cfg)


if __name__ == "__main__":
    main()
