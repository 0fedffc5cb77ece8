"""The ``generate`` stage: plants + LQI experts -> versioned demonstrations in ``data/demos``."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from generalist_control.common.sections import as_dict
from generalist_control.common.stage_main import stage_main
from generalist_control.data.demos import check_data_dir, write_demos
from generalist_control.data.generation import build_manifest, generate_demos
from generalist_control.plants.catalog import check_tags, plants_from_config

__all__ = ["main", "run"]

log = logging.getLogger(__name__)


def run(cfg: DictConfig) -> dict[str, Any]:
    """Validate the config (tags the policy takes too), generate and write; the manifest."""
    systems, data = as_dict(cfg.systems), as_dict(cfg.data)
    plants = plants_from_config(systems)
    check_tags(plants, cfg.model.plant.n_tags)
    if "OPENBLAS_CORETYPE" not in os.environ:
        log.warning(
            "numerics not pinned: the data's last bits depend on this CPU's BLAS kernels, so "
            "DVC may see them as changed; `dvc repro generate` pins them (docs/pipeline.md)"
        )
    out_dir = Path(cfg.paths.data_dir)
    check_data_dir(out_dir)  # refuse a folder of someone else's files before any work
    demos = generate_demos(plants, data)
    manifest = build_manifest(plants, demos, data, {"systems": systems, "data": data})
    write_demos(out_dir, demos, manifest)
    log.info(
        "wrote %d demonstrations (%d trajectories, %d plants) to %s, %s",
        manifest["n_demonstrations"],
        manifest["n_trajectories"],
        len(plants),
        out_dir,
        manifest["content_hash"],
    )
    return manifest


@stage_main("config")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``generate`` stage."""
    run(cfg)


if __name__ == "__main__":
    main()
