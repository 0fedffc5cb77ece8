"""Add a plant to a trained policy: ``python adapt.py plant=<name or path>`` (``gc-adapt``).

The policy gains a tag for the plant and only that row is learned (docs/training.md).
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from generalist_control.adaptation import adapt
from generalist_control.adaptation.request import read_request
from generalist_control.common.stage_main import stage_main
from generalist_control.common.stop_signals import exiting_on_signals

__all__ = ["main", "run"]


def run(cfg: DictConfig) -> dict[str, Any]:
    """Adapt the configured policy to ``cfg.plant``; return the adaptation's record."""
    plain = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    stamp = datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    run_dir = Path(cfg.run_dir) if cfg.run_dir else Path("outputs/adapt") / stamp
    record, _ = adapt(read_request(plain, run_dir))  # type: ignore[arg-type]
    return record


@stage_main("adapt")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: adapt, return the kept closed-loop score; SIGTERM exits 143."""
    with exiting_on_signals("adapt: nothing was published"):
        return float(run(cfg)["closed_loop"]["kept"])


if __name__ == "__main__":
    main()
