"""Add a plant to a trained policy: ``python -m generalist_control.adapt plant=<name or path>``.

Also ``python adapt.py`` at the root and ``gc-adapt``. The policy gains a tag for the plant
and only that row is learned (:mod:`generalist_control.adaptation`; docs/training.md,
"Adding a plant to a trained policy").
"""

from __future__ import annotations

import signal
import sys
from datetime import datetime
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from generalist_control.adaptation import adapt
from generalist_control.adaptation.request import read_request
from generalist_control.adaptation.run_folder import Stopped, sigterm_raises
from generalist_control.common.stage_main import stage_main

__all__ = ["main", "run"]


def _run_dir(cfg: DictConfig) -> Path:
    """``run_dir``, else a new ``outputs/adapt/<time>``."""
    if cfg.run_dir:
        return Path(cfg.run_dir)
    return Path("outputs/adapt") / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")


def run(cfg: DictConfig) -> dict[str, Any]:
    """Adapt the configured policy to ``cfg.plant``; return the adaptation's record."""
    plain = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    record, _ = adapt(read_request(plain, _run_dir(cfg)))  # type: ignore[arg-type]
    return record


@stage_main("adapt")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: adapt, and return the kept closed-loop score (lower is better).

    SIGTERM ends it as SIGINT does (exit 143, the MLflow run KILLED). Hydra writes no folder
    (``conf/adapt.yaml``): a refused or stopped adaptation leaves none.
    """
    try:
        with sigterm_raises():
            return float(run(cfg)["closed_loop"]["kept"])
    except Stopped:
        print("adapt: stopped by SIGTERM; nothing was published", file=sys.stderr)
        sys.exit(128 + signal.SIGTERM)


if __name__ == "__main__":
    main()
