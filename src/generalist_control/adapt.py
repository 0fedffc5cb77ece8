"""Add a plant to a trained policy: ``python -m generalist_control.adapt plant=<name or path>``.

Also ``python adapt.py`` at the root and ``gc-adapt``. The policy (``policy=``, default the
pipeline's ``models/policy.ckpt``) gains a tag for the plant; only that tag's embedding row is
learned, from the plant's LQI demonstrations (or a recording, ``demos=``) and DAgger rounds
on the plant; the result is a new policy file in ``run_dir`` and a new version of the
registered model (``docs/training.md``, "Adding a plant to a trained policy"). The work is
:func:`generalist_control.training.adapt.adapt`.
"""

from __future__ import annotations

from typing import Any

import hydra
from omegaconf import DictConfig

from generalist_control.common.paths import HYDRA_CONFIG_PATH
from generalist_control.training.adapt import adapt

__all__ = ["main", "run"]


def run(cfg: DictConfig) -> dict[str, Any]:
    """Adapt the configured policy to ``cfg.plant``; return the adaptation's record."""
    record, _ = adapt(cfg)
    return record


@hydra.main(version_base="1.3", config_path=HYDRA_CONFIG_PATH, config_name="adapt")
def main(cfg: DictConfig) -> float:
    """Hydra entry point: adapt, and return the kept closed-loop score (lower is better)."""
    return float(run(cfg)["closed_loop"]["kept"])


if __name__ == "__main__":
    main()
