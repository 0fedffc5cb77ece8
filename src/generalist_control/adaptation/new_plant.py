"""The plant a policy is adapted to: its file checked against the policy; its demonstrations.

``plant=`` names a catalogue plant or a plant YAML. Demonstrations are generated from its LQI
or recorded from any controller (``demos=``): one row per sample (Parquet or CSV) with
``traj``, ``t``, the states ``x0 .. x{n-1}``, ``r``, ``y``, ``u`` (docs/training.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from generalist_control.common.paths import conf_dir
from generalist_control.data.demos import content_hash
from generalist_control.data.generation import generate_demos
from generalist_control.data.windows import Windows, build_windows, integral_of_error
from generalist_control.deploy.runtime_plants import integral_facts
from generalist_control.plants.catalog import available_plants
from generalist_control.plants.config import plant_from_config, read_plant_file
from generalist_control.plants.definition import Plant, PlantConfigError, pad_states
from generalist_control.simulation.lqi import design_lqi

__all__ = [
    "COLUMNS",
    "NewPlant",
    "RecordedDemos",
    "RecordingError",
    "generated_windows",
    "load_new_plant",
    "plant_meta",
    "read_recorded",
    "write_recorded",
]


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
    plant = plant_from_config(path.stem, read_plant_file(path), path)
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
    name, facts = plant.name, integral_facts(plants=[plant])
    return {
        **meta,
        "tags": {**meta["tags"], name: int(plant.tag)},
        "orders": {**meta["orders"], name: int(plant.order)},
        **{k: {**meta.get(k, {}), **v} for k, v in facts.items()},
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


#: The columns besides the states ``x0 .. x{n-1}``.
COLUMNS = ("traj", "t", "r", "y", "u")

#: Relative tolerance on the sample spacing (times ``dt``).
DT_TOLERANCE = 1e-6


class RecordingError(ValueError):
    """A recorded-demonstrations file that cannot be used; the message names the fix."""


@dataclass(frozen=True)
class RecordedDemos:
    """The windows of a recorded file (tagged as asked) and what they came from."""

    windows: Windows
    trajectories: int
    samples: int


def _table(path: Path) -> pd.DataFrame:
    """The recording's rows, or a :class:`RecordingError` naming the fix."""
    if not path.is_file():
        raise RecordingError(f"no recorded demonstrations at {path}: give demos=<file>")
    if path.suffix in (".parquet", ".csv"):
        try:
            return pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
        except (OSError, ValueError) as exc:
            raise RecordingError(
                f"{path}: not a readable {path.suffix[1:]} file ({exc}); write the recording "
                "again (columns traj, t, x0..x{n-1}, r, y, u; docs/training.md)"
            ) from None
    raise RecordingError(
        f"{path}: recorded demonstrations must be a .parquet or .csv file (columns traj, t, "
        "x0..x{n-1}, r, y, u; docs/training.md)"
    )


def _checked(df: pd.DataFrame, path: Path, plant: Plant) -> pd.DataFrame:
    """The columns the plant needs, present, numeric and finite; no stray state columns."""
    states = [f"x{i}" for i in range(plant.order)]
    wanted = [*COLUMNS[:2], *states, *COLUMNS[2:]]
    missing = [c for c in wanted if c not in df.columns]
    if missing:
        raise RecordingError(
            f"{path} lacks the columns {missing}; a recording of plant '{plant.name}' "
            f"({plant.order} states) has the columns {wanted}, one row per sample"
        )
    extra = sorted(
        c for c in df.columns if c.startswith("x") and c[1:].isdigit() and c not in states
    )
    if extra:
        raise RecordingError(
            f"{path} has the state columns {extra} beyond plant '{plant.name}''s {plant.order} "
            f"states ({states}): record the plant's own states, or adapt to the plant they "
            "belong to"
        )
    try:
        values = df[wanted].astype(np.float64)
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{path}: a column of {wanted} is not numeric ({exc})") from None
    bad = ~np.isfinite(values.to_numpy())
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise RecordingError(
            f"{path}: column '{wanted[col]}' is NaN or infinite at row {int(row)} (and "
            f"{int(bad.sum()) - 1} more values): drop or repair those samples (a trajectory cut "
            "short is fine)"
        )
    return values


def _trajectories(
    values: pd.DataFrame, path: Path, plant: Plant, horizon: int
) -> list[np.ndarray]:
    """Each trajectory's rows in time order, checked to be ``plant.dt`` apart."""
    out = []
    for traj, group in values.groupby("traj", sort=True):
        rows = group.sort_values("t").to_numpy()
        step = np.diff(rows[:, 1])
        if len(rows) <= horizon:
            raise RecordingError(
                f"{path}: trajectory {traj:g} has {len(rows)} samples; each needs more than "
                f"the policy's horizon ({horizon})"
            )
        if not np.allclose(step, plant.dt, rtol=DT_TOLERANCE, atol=0.0):
            worst = float(step[np.argmax(np.abs(step - plant.dt))])
            raise RecordingError(
                f"{path}: trajectory {traj:g} has samples {worst:g} s apart; plant "
                f"'{plant.name}' and the policy run at dt = {plant.dt:g} s. Record at that "
                "sample time (or resample the recording to it)"
            )
        out.append(rows)
    return out


def read_recorded(
    path: str | Path, plant: Plant, tag: int, history: int, horizon: int, controls: bool = False
) -> RecordedDemos:
    """The windows of a recorded file of ``plant``, tagged ``tag``, with the error integral.

    ``controls``: also the previous-control channel (``model.channels``).

    Raises
    ------
    RecordingError
        Naming the fix: an unknown suffix, missing or non-numeric columns, NaN or inf,
        samples not ``plant.dt`` apart, too short a trajectory, extra state columns.
    """
    path = Path(path)
    values = _checked(_table(path), path, plant)
    if values.empty:
        raise RecordingError(f"{path} holds no samples")
    n, parts = plant.order, []
    trajs = _trajectories(values, path, plant, horizon)
    for i, rows in enumerate(trajs):  # in the order of their ids
        x, r, y, u = (rows[None, :, 2 : 2 + n], *(rows[None, :, 2 + n + k] for k in range(3)))
        z = integral_of_error(r, y, plant.dt)
        w = build_windows(pad_states(x), r, u, np.full(1, tag), np.full(1, n), history, horizon,
                          z, controls)  # fmt: skip
        parts.append(Windows(w.state, w.mask, w.ref, w.tag, w.target, w.traj + i))
    fields = ("state", "mask", "ref", "tag", "target", "traj")
    windows = Windows(**{k: np.concatenate([getattr(w, k) for w in parts]) for k in fields})
    return RecordedDemos(windows, trajectories=len(trajs), samples=len(values))


def write_recorded(
    path: str | Path, plant: Plant, x: np.ndarray, r: np.ndarray, y: np.ndarray, u: np.ndarray
) -> Path:
    """Write ``x`` (B, N, >= n; padding dropped), ``r``, ``y``, ``u`` (B, N) as a recording."""
    path = Path(path)
    B, N = r.shape
    cols: dict[str, np.ndarray] = {
        "traj": np.repeat(np.arange(B), N),
        "t": np.tile(np.arange(N) * plant.dt, B),
    }
    for i in range(plant.order):
        cols[f"x{i}"] = x[:, :N, i].ravel()
    cols.update(r=r.ravel(), y=y[:, :N].ravel(), u=u.ravel())
    df = pd.DataFrame(cols)
    if path.suffix == ".parquet":
        df.to_parquet(path, index=False)
    else:
        df.to_csv(path, index=False, float_format="%.17g")
    return path
