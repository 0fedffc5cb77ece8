"""The plant catalogue: plant files under ``conf/plants``, the sets in ``conf/systems``."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import yaml
from omegaconf import OmegaConf

from generalist_control.common.paths import conf_dir
from generalist_control.common.sections import require_int
from generalist_control.plants.config import plant_from_config, read_plant_file
from generalist_control.plants.definition import Plant, PlantConfigError

__all__ = [
    "UnknownPlantError",
    "available_plants",
    "catalogue_tags",
    "check_tags",
    "load_plant",
    "plants_from_config",
    "tag_count",
]


_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class UnknownPlantError(KeyError):
    """A plant name that is not in the catalogue."""

    def __str__(self) -> str:  # KeyError quotes its message; show it plainly
        return str(self.args[0])


def available_plants() -> list[str]:
    """Names of all plant files in ``conf/plants``."""
    return sorted(p.stem for p in (conf_dir() / "plants").glob("*.yaml"))


def _unknown(name: str, known: Iterable[str]) -> UnknownPlantError:
    return UnknownPlantError(
        f"unknown plant '{name}'; known plants: {', '.join(sorted(known))}. "
        "Add conf/plants/<name>.yaml and list it in a conf/systems set to define a new one."
    )


def load_plant(name: str) -> Plant:
    """Load and validate one plant from ``conf/plants/<name>.yaml``."""
    path = conf_dir() / "plants" / f"{name}.yaml"
    if not path.is_file():
        raise _unknown(name, available_plants())
    return plant_from_config(name, read_plant_file(path), path)


def plants_from_config(systems: Mapping[str, Any]) -> list[Plant]:
    """Validated plants of a composed ``systems`` config (plain types), ordered by tag.

    ``systems.include`` (a list of names, optional) keeps only those plants of the set.

    Raises
    ------
    UnknownPlantError
        If ``include`` names a plant that is not in the set.
    PlantConfigError
        If a plant is invalid, two plants share a tag, or ``include`` is an empty list (it
        names no plant; leaving the key out means every plant of the set).
    """
    entries: Mapping[str, Any] = systems.get("plants") or {}
    if not entries:
        raise PlantConfigError(f"systems set '{systems.get('name', '?')}' lists no plants")
    include = systems.get("include")
    if include is not None and len(include) == 0:
        raise PlantConfigError(
            f"systems.include=[] names no plant of set '{systems.get('name', '?')}'; drop the "
            "key for every plant of the set, or name plants, e.g. systems.include=[cstr]"
        )
    if include:
        for name in include:
            if name not in entries:
                raise _unknown(name, entries)
        entries = {k: v for k, v in entries.items() if k in include}
    plants = sorted((plant_from_config(k, v) for k, v in entries.items()), key=lambda p: p.tag)
    seen: dict[int, str] = {}
    for p in plants:
        if p.tag in seen:
            raise PlantConfigError(
                f"plants '{seen[p.tag]}' and '{p.name}' share tag {p.tag}; tags must be unique"
            )
        seen[p.tag] = p.name
    return plants


def check_tags(plants: Iterable[Plant], n_tags: Any) -> None:
    """Refuse plants whose tag the policy cannot take: tags must lie in ``0..n_tags-1``.

    ``n_tags`` is ``model.plant.n_tags``, the size of the policy's one-hot tag input.

    Raises
    ------
    PlantConfigError
        Naming every such plant, its tag, the allowed range and the fixes.
    ValueError
        If ``n_tags`` is not a positive integer.
    """
    n = require_int("model.plant.n_tags", n_tags)
    bad = [p for p in plants if not 0 <= p.tag < n]
    if not bad:
        return
    which = ", ".join(f"'{p.name}' (tag {p.tag})" for p in bad)
    one = len(bad) == 1
    fixes = [f"give {'it a free tag' if one else 'them free tags'} in 0..{n - 1}"]
    top = max(p.tag for p in bad)
    if top >= n:
        fixes.insert(
            0,
            f"raise model.plant.n_tags to at least {top + 1} (conf/model/, the same for generate "
            "and train)",
        )
    raise PlantConfigError(
        f"{'plant' if one else 'plants'} {which} {'is' if one else 'are'} outside the "
        f"policy's tags 0..{n - 1} (model.plant.n_tags={n}); {' or '.join(fixes)} "
        "(conf/plants/<name>.yaml, field 'tag')"
    )


def catalogue_tags() -> dict[str, int]:
    """Every catalogue plant's tag, by name (the ``tag`` field of ``conf/plants/*.yaml``).

    Read with libyaml (every config that sizes a policy resolves this: 13 ms for 26 files,
    against 175 ms through ``OmegaConf.load``).
    """
    tags = {}
    for name in available_plants():
        text = (conf_dir() / "plants" / f"{name}.yaml").read_text()
        data = yaml.load(text, Loader=_LOADER)
        tag = data.get("tag") if isinstance(data, dict) else None
        tags[name] = require_int(f"conf/plants/{name}.yaml: field 'tag'", tag, minimum=0)
    return tags


def tag_count(n_tags: Any = None) -> int:
    """The policy's tag rows: ``n_tags`` as given, or (None) one per catalogue plant.

    The catalogue's tags must then be ``0 .. N - 1`` for N plant files.

    Raises
    ------
    PlantConfigError
        Two plant files share a tag, or the tags leave a row no plant has (a gap), naming
        the files and the tag to give.
    ValueError
        An ``n_tags`` that is not a positive integer.
    """
    if n_tags is not None:
        return require_int("model.plant.n_tags", n_tags)
    tags = catalogue_tags()
    free = sorted(set(range(len(tags))) - set(tags.values()))
    owner: dict[int, str] = {}
    for name, tag in sorted(tags.items()):
        if tag in owner:
            raise PlantConfigError(
                f"conf/plants/{owner[tag]}.yaml and conf/plants/{name}.yaml share tag {tag}; "
                f"tags must be unique: give one of them the free tag {free[0]} (field 'tag')"
            )
        owner[tag] = name
    if free:
        above = sorted((t, n) for t, n in owner.items() if t >= len(tags))
        which = ", ".join(f"'{n}' (tag {t})" for t, n in above)
        unused = f"tag{'s' if len(free) > 1 else ''} {', '.join(map(str, free))}"
        raise PlantConfigError(
            f"the catalogue's tags leave {unused} unused (a policy row no plant trains): the "
            f"{len(tags)} files of conf/plants must have tags 0..{len(tags) - 1}; give {which} "
            f"{unused} (field 'tag')"
        )
    return len(tags)


# ``${gc.tag_count:}`` in conf/model/plant/*.yaml
OmegaConf.register_new_resolver("gc.tag_count", tag_count, replace=True)
