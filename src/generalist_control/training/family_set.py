"""Training over plant families beside the catalogue (``train_families``, issue 50).

A family's plants take the tags after the catalogue's, rebuilt from its manifest as drawn.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from generalist_control.data.demos import DemoSet, load_demos, read_manifest
from generalist_control.plants.definition import Plant
from generalist_control.plants.families import plant_from_record
from generalist_control.training.settings import FamilyTraining

__all__ = ["FamilySet", "join_demos", "with_rows"]


def join_demos(first: DemoSet, second: DemoSet, offset: int) -> DemoSet:
    """``first``'s trajectories, then ``second``'s with their tags raised by ``offset``.

    Raises
    ------
    ValueError
        If the two sets differ in sample time or trajectory length, or carry variants.
    """
    if first.dt != second.dt or first.r.shape[1] != second.r.shape[1]:
        raise ValueError(
            f"a family's demonstrations must match the catalogue's sample time and duration: "
            f"dt {second.dt} against {first.dt}, {second.r.shape[1]} samples against "
            f"{first.r.shape[1]} (generate both with the same data.duration)"
        )
    if first.variant is not None or second.variant is not None:
        raise ValueError("train_families does not take variant data (data.variants)")
    fields = ("x", "r", "u", "y", "order", "plant", "amplitude", "family")
    joined = {k: np.concatenate([getattr(first, k), getattr(second, k)]) for k in fields}
    tag = np.concatenate([first.tag, second.tag + offset])
    return DemoSet(**joined, tag=tag, dt=first.dt)


@dataclass(frozen=True)
class FamilySet:
    """The families trained on, their plants tagged after the catalogue's."""

    dirs: tuple[Path, ...]  #: the families' data folders, in tag order
    plants: list[Plant]  #: every family plant, tag ``offset + i``
    offset: int  #: the first family tag (the catalogue's tag count)
    spec: FamilyTraining | None = None

    @classmethod
    def load(
        cls, dirs: Sequence[str | Path], offset: int, spec: FamilyTraining | None = None
    ) -> FamilySet:
        """The families at ``dirs`` (each checked against its manifest), tagged from ``offset``.

        Raises
        ------
        generalist_control.data.demos.MissingDataError
            A folder holds no dataset (with the command that makes it).
        ValueError
            A dataset that is not a family's (its manifest has no ``plant_family``).
        """
        plants: list[Plant] = []
        for d in (Path(p) for p in dirs):
            _, manifest = load_demos(d, verify=False)
            block = manifest.get("plant_family")
            if not isinstance(block, dict):
                raise ValueError(
                    f"{d} holds demonstrations but not a plant family's (its manifest has no "
                    "plant_family block); make one with python -m "
                    "generalist_control.generate_families"
                )
            start = offset + len(plants)
            for name in sorted(block["plants"], key=lambda n: block["plants"][n]["tag"]):
                p = plant_from_record(block, name, float(manifest["dt"]))
                plants.append(dataclasses.replace(p, tag=start + p.tag))
        return cls(tuple(Path(p) for p in dirs), plants, int(offset), spec)

    @property
    def rows(self) -> int:
        """The policy's rows with the families: the catalogue's, then one per family plant."""
        return self.offset + len(self.plants)

    @property
    def names(self) -> list[str]:
        """The family plants' names."""
        return [p.name for p in self.plants]

    def joined(self, demos: DemoSet, manifest: dict[str, Any]) -> tuple[DemoSet, dict[str, Any]]:
        """The catalogue's demonstrations with every family's; the manifest's hash over all."""
        hashes = [str(manifest.get("content_hash", ""))]
        start = self.offset
        for d in self.dirs:
            fam, fam_manifest = load_demos(d)
            demos = join_demos(demos, fam, start)
            start += len(fam_manifest["plant_family"]["plants"])
            hashes.append(str(fam_manifest["content_hash"]))
        joint = "sha256:" + hashlib.sha256("\0".join(hashes).encode()).hexdigest()
        return demos, {**manifest, "content_hash": joint, "families": [str(d) for d in self.dirs]}

    def record(self) -> list[dict[str, Any]]:
        """Per family: its folder, name, seed and plant count (the policy's meta).

        Then the validation draw's (``dir`` None), so that no report tests on it.
        """
        out = []
        for d in self.dirs:
            block = read_manifest(d)["plant_family"]
            out.append({"dir": str(d), "name": block["name"], "seed": int(block["seed"]),
                        "plants": len(block["plants"])})  # fmt: skip
        if self.spec is not None and (v := self.spec.validation) is not None:
            generator = v["generator"]
            out.append({"dir": None, "name": generator["name"], "seed": int(generator["seed"]),
                        "plants": int(v["count"])})  # fmt: skip
        return out


def with_rows(model: dict[str, Any], families: FamilySet | None) -> dict[str, Any]:
    """The network's config with a plant part of at least one row per training plant."""
    plant = model.get("plant")
    if families is None or not isinstance(plant, dict) or "n_tags" not in plant:
        return model
    return {**model, "plant": {**plant, "n_tags": max(int(plant["n_tags"]), families.rows)}}
