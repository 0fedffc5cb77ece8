"""The plant a trained policy is adapted to: loaded, checked against the policy, demonstrated.

``plant=`` names a catalogue plant (``conf/plants/<name>.yaml``) or a path to a YAML file in
the catalogue's schema (``conf/plants/README.md``; the file's stem is the plant's name).
Before anything is written it is checked against the policy: a name the policy already
knows, a file ``tag`` the policy uses, another sample time, an order above
:data:`~generalist_control.plants.plant.MAX_ORDER` or a plant unfit for LQI is refused,
naming the fix. The plant is then given the policy's new row as its tag
(:attr:`NewPlant.plant`), so that the data stage's code, the sampler and the labeller tag
its windows with that row.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
from omegaconf import OmegaConf

from generalist_control.common.paths import conf_dir
from generalist_control.data.demos import content_hash
from generalist_control.data.generation import generate_demos
from generalist_control.data.windows import Windows
from generalist_control.plants.catalog import available_plants
from generalist_control.plants.config import plant_from_config
from generalist_control.plants.plant import Plant, PlantConfigError
from generalist_control.simulation.lqi import design_lqi

__all__ = ["NewPlant", "generated_windows", "load_new_plant", "plant_meta", "retagged"]

#: Suffixes that make ``plant=`` a path rather than a catalogue name.
_SUFFIXES = (".yaml", ".yml")


@dataclass(frozen=True)
class NewPlant:
    """A plant to add, as loaded (``file_tag``: its file's ``tag``) and retagged.

    Attributes
    ----------
    plant : Plant
        The plant with ``tag`` set to the policy's new row.
    file_tag : int
        The ``tag`` its file gives.
    path : Path
        The YAML file it was read from (a catalogue file or the user's).
    in_catalogue : bool
        Whether ``plant=`` named a catalogue plant.
    """

    plant: Plant
    file_tag: int
    path: Path
    in_catalogue: bool

    @property
    def name(self) -> str:
        """The plant's name (the file's stem)."""
        return self.plant.name


def _read(spec: str) -> tuple[Path, bool]:
    """The plant file ``spec`` names and whether it is a catalogue plant."""
    if spec.endswith(_SUFFIXES) or "/" in spec:
        path = Path(spec)
        if not path.is_file():
            raise PlantConfigError(
                f"plant={spec}: no such file; give a catalogue name "
                f"({', '.join(available_plants())}) or the path of a plant YAML "
                "(conf/plants/README.md)"
            )
        if path.stem in available_plants():
            raise PlantConfigError(
                f"plant={spec}: the file's stem '{path.stem}' is the name of a catalogue plant "
                f"(conf/plants/{path.stem}.yaml); rename the file (its stem is the plant's name)"
            )
        return path, False
    path = conf_dir() / "plants" / f"{spec}.yaml"
    if not path.is_file():
        raise PlantConfigError(
            f"plant={spec}: unknown plant; known: {', '.join(available_plants())}; or give the "
            "path of a plant YAML in the catalogue's schema (conf/plants/README.md)"
        )
    return path, True


def load_new_plant(spec: str, meta: Mapping[str, Any], dt: float) -> NewPlant:
    """Load ``plant=spec`` and check it against the policy's ``meta``; nothing is written.

    Raises
    ------
    PlantConfigError
        The file is missing or invalid (an order above ``MAX_ORDER`` included), the plant is
        unfit for LQI, its name is already one of the policy's plants, its file's ``tag`` is
        a tag the policy uses, or its ``dt`` is not the policy's.
    """
    path, in_catalogue = _read(str(spec))
    raw = cast(dict[str, Any], OmegaConf.to_container(OmegaConf.load(path), resolve=True))
    plant = plant_from_config(path.stem, raw)
    tags = {str(k): int(v) for k, v in meta["tags"].items()}
    if plant.name in tags:
        raise PlantConfigError(
            f"plant '{plant.name}' is already a plant of this policy (tag {tags[plant.name]}): "
            "there is nothing to add. Evaluate it directly, or give the new plant its own name "
            "(its file's stem)"
        )
    used = set(tags.values()) | {int(r["file_tag"]) for r in meta.get("adapted", {}).values()}
    if plant.tag in used:
        raise PlantConfigError(
            f"plant '{plant.name}': its file's tag {plant.tag} is a tag this policy uses; give "
            f"it a tag the policy does not use (it uses {sorted(used)}), e.g. {max(used) + 1}"
        )
    if not np.isclose(plant.dt, dt, rtol=1e-9, atol=0.0):
        raise PlantConfigError(
            f"plant '{plant.name}' has dt = {plant.dt:g} s, the policy runs at dt = {dt:g} s: a "
            "policy's windows have one sample time; model the plant at that dt"
        )
    design_lqi(plant)  # refuses a plant unfit for LQI, naming why
    return NewPlant(plant, plant.tag, path, in_catalogue)


def retagged(new: NewPlant, tag: int) -> NewPlant:
    """``new`` with its plant on the policy's row ``tag``."""
    return dataclasses.replace(new, plant=dataclasses.replace(new.plant, tag=int(tag)))


def plant_meta(meta: Mapping[str, Any], plant: Plant, record: Mapping[str, Any]) -> dict[str, Any]:
    """The policy's meta with ``plant`` (tagged with its row) added, and its ``adapted`` record.

    Adds what the runtime needs of a plant the catalogue may not hold: its order, its
    output row ``C`` (of the linearisation for a nonlinear plant) and the sign of its
    expert's ``-Ki`` (anti-windup), as training stores them for its own plants.
    """
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
    """The plant's LQI demonstrations by the data stage's recipe, as windows, and their facts.

    The data config's amplitude grid and families, this plant only
    (:func:`~generalist_control.data.generation.generate_demos`), cut to the policy's window.
    """
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
