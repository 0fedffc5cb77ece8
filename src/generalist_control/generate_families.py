"""The ``generate_families`` stage: a plant family -> LQI experts -> demonstrations.

A stage of its own, so that the catalogue's ``data/demos`` does not change with a family.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, cast

from omegaconf import DictConfig, OmegaConf

from generalist_control.common.sections import require_int
from generalist_control.common.stage_main import stage_main
from generalist_control.data.demos import check_data_dir, write_demos
from generalist_control.data.generation import build_manifest, generate_demos
from generalist_control.simulation.family_draw import draw_family, read_families

__all__ = ["main", "run"]

log = logging.getLogger(__name__)


def _data(cfg: DictConfig, demos: Any) -> dict[str, Any]:
    """The data config: sizes and duration from ``data``, references from ``families.demos``."""
    if not isinstance(demos, dict) or "amplitudes" not in demos:
        raise ValueError("families.demos must give amplitudes (and optionally families)")
    unknown = sorted(set(demos) - {"amplitudes", "families"})
    if unknown:
        raise ValueError(
            f"families.demos has unknown keys {unknown}; it takes amplitudes, families"
        )
    sizes = {k: cfg.data[k] for k in ("history", "horizon", "duration")}
    require_int("data.history", sizes["history"])
    require_int("data.horizon", sizes["horizon"])
    return {**sizes, **demos}


def run(cfg: DictConfig) -> dict[str, Any]:
    """Validate the config, draw the family, generate and write; the manifest."""
    families = cast(dict[str, Any], OmegaConf.to_container(cfg.families, resolve=True))
    family, settings = read_families(families)
    data = _data(cfg, settings.demos)
    out_dir = Path(settings.data_dir)
    check_data_dir(out_dir)  # refuse a folder of someone else's files before any work
    draw = draw_family(family, settings.count, settings.checks)
    log.info("plant family '%s': %s", family.name, draw.counts())
    plants = draw.plants
    demos = generate_demos(plants, data)
    recipe = {k: v for k, v in families.items() if k != "data_dir"}  # what, not where
    config = {"families": recipe, "data": data}
    manifest = build_manifest(plants, demos, data, config)
    manifest["plant_family"] = draw.record()
    write_demos(out_dir, demos, manifest)
    log.info("wrote %d demonstrations (%d trajectories, %d plants) to %s, %s",
             manifest["n_demonstrations"], manifest["n_trajectories"], len(plants), out_dir,
             manifest["content_hash"])  # fmt: skip
    return manifest


@stage_main("generate_families")
def main(cfg: DictConfig) -> None:
    """Hydra entry point of the ``generate_families`` stage."""
    run(cfg)


if __name__ == "__main__":
    main()
