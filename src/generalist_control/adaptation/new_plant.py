"""The plant a policy is adapted to: its file read once, checked against the policy, demonstrated.

``plant=`` names a catalogue plant or the path of a YAML file in the catalogue's schema.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from generalist_control.common.paths import conf_dir
from generalist_control.data.demos import content_hash
from generalist_control.data.generation import generate_demos
from generalist_control.data.windows import Windows
from generalist_control.plants.catalog import available_plants
from generalist_control.plants.config import plant_from_config
from generalist_control.plants.definition import Plant, PlantConfigError
from generalist_control.simulation.lqi import design_lqi

__all__ = ["NewPlant", "generated_windows", "load_new_plant", "plant_meta"]


@dataclass(frozen=True)
class NewPlant:
    """The plant to add, on the policy's row (``plant.tag``), and where it came from."""

    plant: Plant
    file_tag: int  #: the ``tag`` its file gives
    path: Path  #: the YAML file it was read from
    in_catalogue: bool  #: ``plant=`` named a catalogue plant

    @property
    def name(self) -> str:
        """The plant's name (the file's stem)."""
        return self.plant.name

    def on_row(self, tag: int) -> NewPlant:
        """The same plant on the policy's row ``tag``."""
        return dataclasses.replace(self, plant=dataclasses.replace(self.plant, tag=int(tag)))


def _path(spec: str) -> tuple[Path, bool]:
    """The plant file ``spec`` names and whether it is a catalogue plant (its stem: the name)."""
    known = available_plants()
    if not spec.endswith((".yaml", ".yml")) and "/" not in spec:
        path = conf_dir() / "plants" / f"{spec}.yaml"
        if not path.is_file():
            raise PlantConfigError(
                f"plant={spec}: unknown plant; known: {', '.join(known)}; or give the path of "
                "a plant YAML in the catalogue's schema (conf/plants/README.md)"
            )
        return path, True
    path = Path(spec)
    if not path.is_file():
        raise PlantConfigError(
            f"plant={spec}: no such file; give a catalogue name ({', '.join(known)}) or the "
            "path of a plant YAML (conf/plants/README.md)"
        )
    if path.stem in known:
        raise PlantConfigError(
            f"{path}: the file's stem '{path.stem}' is the name of a catalogue plant "
            f"(conf/plants/{path.stem}.yaml); rename the file (its stem is the plant's name)"
        )
    return path, False


def load_new_plant(spec: str, meta: Mapping[str, Any]) -> NewPlant:
    """Load ``plant=spec`` and check it against the policy's ``meta``; nothing is written.

    Raises
    ------
    PlantConfigError
        Naming the file: missing, not YAML, invalid or unfit for LQI; its name or ``tag``
        already the policy's, or its ``dt`` not the policy's.
    """
    path, in_catalogue = _path(spec)
    try:
        raw = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except (yaml.YAMLError, OmegaConfBaseException) as exc:
        raise PlantConfigError(f"{path}: not a YAML file ({exc})") from None
    plant = plant_from_config(path.stem, raw, path)
    tags = {str(k): int(v) for k, v in meta["tags"].items()}
    used = set(tags.values()) | {int(r["file_tag"]) for r in meta.get("adapted", {}).values()}
    dt = float(meta["dt"])
    if plant.name in tags:
        problem = (
            f"plant '{plant.name}' is already a plant of this policy (tag {tags[plant.name]}): "
            "there is nothing to add. Evaluate it directly, or give the new plant its own name "
            "(its file's stem)"
        )
    elif plant.tag in used:
        problem = (
            f"its tag {plant.tag} is a tag this policy uses; give it a tag the policy does not "
            f"use (it uses {sorted(used)}), e.g. {max(used) + 1}"
        )
    elif not np.isclose(plant.dt, dt, rtol=1e-9, atol=0.0):
        problem = (
            f"dt = {plant.dt:g} s, the policy runs at dt = {dt:g} s: a policy's windows have "
            "one sample time; model the plant at that dt"
        )
    else:
        try:
            design_lqi(plant)  # refuses a plant unfit for LQI, naming why
        except PlantConfigError as exc:
            problem = str(exc)
        else:
            return NewPlant(plant, plant.tag, path, in_catalogue)
    raise PlantConfigError(f"{path}: {problem}")


def plant_meta(meta: Mapping[str, Any], plant: Plant, record: Mapping[str, Any]) -> dict[str, Any]:
    """The policy's meta with ``plant`` added as training stores a plant, and its ``record``."""
    name = plant.name
    return {
        **meta,
        "tags": {**meta["tags"], name: int(plant.tag)},
        "orders": {**meta["orders"], name: int(plant.order)},
        "outputs": {**meta.get("outputs", {}), name: [float(c) for c in plant.C[0]]},
        "integral_directions": {
            **meta.get("integral_directions", {}),
            name: float(np.sign(-design_lqi(plant).Ki)),
        },
        "adapted": {**meta.get("adapted", {}), name: dict(record)},
    }


def generated_windows(
    plant: Plant, data: Mapping[str, Any], history: int, horizon: int, channels: tuple[str, ...]
) -> tuple[Windows, dict[str, Any]]:
    """The plant's LQI demonstrations by the data stage's recipe (``data``), as windows."""
    data = {**data, "history": history, "horizon": horizon}
    demos = generate_demos([plant], data, progress=False)
    windows = demos.windows(
        history, horizon, "integral" in channels, "previous_control" in channels
    )
    facts = {
        "source": "generated",
        "expert": "LQI",
        "trajectories": int(len(demos.r)),
        "windows": int(len(windows)),
        "content_hash": content_hash(demos, {"plant": plant.name, "data": dict(data)}),
    }
    return windows, facts
