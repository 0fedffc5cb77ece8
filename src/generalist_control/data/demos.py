"""The demonstration dataset on disk: ``trajectories.parquet`` plus ``manifest.json``.

Written atomically; loading checks the manifest's digest, the file's SHA-256, the table's shape
and the content hash recomputed from the arrays.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from generalist_control.common.atomic import (
    check_replaceable,
    publish_directory,
    recover,
    staging_directory,
)
from generalist_control.common.paths import GENERATE_COMMAND
from generalist_control.data.windows import Windows, build_windows, integral_of_error
from generalist_control.plants.definition import MAX_ORDER

__all__ = [
    "OWNED",
    "CorruptDataError",
    "DemoSet",
    "MissingDataError",
    "check_data_dir",
    "content_hash",
    "load_demos",
    "manifest_digest",
    "read_manifest",
    "write_demos",
]

TRAJECTORIES = "trajectories.parquet"
MANIFEST = "manifest.json"
DIGEST = "manifest_digest"  # the manifest's field that seals all the others
FORMAT_VERSION = 2  # 2: a family per trajectory


#: What a dataset folder holds (a folder without a marker holding only these may be replaced).
OWNED: dict[str, str | None] = {TRAJECTORIES: None, MANIFEST: None}


class MissingDataError(FileNotFoundError):
    """The demonstration dataset is missing or incomplete."""


class CorruptDataError(ValueError):
    """The dataset on disk does not match its manifest (changed, truncated or spliced)."""


@dataclass(frozen=True)
class DemoSet:
    """``B`` trajectories of ``N`` samples each, in deviation coordinates.

    ``x`` (B, N, MAX_ORDER) zero-padded; ``amplitude`` the reference's final value; ``variant``
    (with ``data.variants``) 0 for the nominal plant, ``i`` for its ``i``-th variant.
    """

    x: np.ndarray
    r: np.ndarray
    u: np.ndarray
    y: np.ndarray
    tag: np.ndarray
    order: np.ndarray
    plant: np.ndarray
    amplitude: np.ndarray
    dt: float
    family: np.ndarray
    variant: np.ndarray | None = None

    def windows(
        self, history: int, horizon: int, integral: bool = False, controls: bool = False
    ) -> Windows:
        """All training windows of the set, with the ``integral`` and ``controls`` channels."""
        z = integral_of_error(self.r, self.y, self.dt) if integral else None
        return build_windows(
            self.x, self.r, self.u, self.tag, self.order, history, horizon, z, controls
        )


def content_hash(demos: DemoSet, config: dict[str, Any]) -> str:
    """SHA-256 over the arrays' bytes and the canonical JSON of the data config."""
    h = hashlib.sha256()
    for a in (demos.x, demos.r, demos.u, demos.y, demos.amplitude):
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    for a in (demos.tag, demos.order):
        h.update(np.ascontiguousarray(a, dtype="<i8").tobytes())
    h.update("\0".join(demos.plant.tolist()).encode())
    h.update("\0".join(demos.family.tolist()).encode())
    if demos.variant is not None:  # only with data.variants: the default's hash is unchanged
        h.update(np.ascontiguousarray(demos.variant, dtype="<i8").tobytes())
    h.update(json.dumps(config, sort_keys=True, separators=(",", ":")).encode())
    return "sha256:" + h.hexdigest()


def manifest_digest(manifest: Mapping[str, Any]) -> str:
    """SHA-256 over the canonical JSON of every field of ``manifest`` but its digest."""
    body = {k: v for k, v in manifest.items() if k != DIGEST}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def _to_table(demos: DemoSet) -> pa.Table:
    """One row per sample."""
    B, N = demos.r.shape
    rep = lambda a: np.repeat(a, N)  # noqa: E731
    cols: dict[str, Any] = {
        "traj": rep(np.arange(B, dtype=np.int32)),
        "plant": pa.array(rep(demos.plant)).dictionary_encode(),
        "family": pa.array(rep(demos.family)).dictionary_encode(),
        "tag": rep(demos.tag.astype(np.int16)),
        "order": rep(demos.order.astype(np.int8)),
        "amplitude": rep(demos.amplitude),
        "k": np.tile(np.arange(N, dtype=np.int32), B),
        "t": np.tile(np.arange(N) * demos.dt, B),
    }
    for i in range(MAX_ORDER):
        cols[f"x{i}"] = demos.x[:, :, i].ravel()
    cols.update(r=demos.r.ravel(), u=demos.u.ravel(), y=demos.y.ravel())
    if demos.variant is not None:
        cols["variant"] = rep(demos.variant.astype(np.int16))
    return pa.table(cols)


def check_data_dir(out_dir: str | Path) -> None:
    """Refuse (before any work) a ``paths.data_dir`` that holds anything but a dataset."""
    check_replaceable(out_dir, OWNED, "paths.data_dir")


def write_demos(out_dir: str | Path, demos: DemoSet, manifest: dict[str, Any]) -> Path:
    """Write the dataset atomically to ``out_dir``, replacing a previous dataset only.

    Raises
    ------
    generalist_control.common.atomic.ForeignDirectoryError
        If ``out_dir`` holds anything but a dataset's two files; nothing is changed.
    """
    check_data_dir(out_dir)
    with staging_directory(out_dir) as tmp:
        pq.write_table(_to_table(demos), tmp / TRAJECTORIES, compression="zstd")
        digest = hashlib.sha256((tmp / TRAJECTORIES).read_bytes()).hexdigest()
        manifest = {**manifest, "files": {TRAJECTORIES: "sha256:" + digest}}
        manifest[DIGEST] = manifest_digest(manifest)
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
        return publish_directory(tmp, out_dir, OWNED, "paths.data_dir")


def _corrupt(data_dir: Path, what: str) -> CorruptDataError:
    """The error for a dataset that differs from its manifest in ``what``."""
    return CorruptDataError(
        f"the dataset at '{data_dir}' does not match its manifest: {what}. It was changed "
        f"after it was written; regenerate it with: {GENERATE_COMMAND}"
    )


def read_manifest(data_dir: str | Path) -> dict[str, Any]:
    """The dataset's manifest, checked against its own digest (every field is covered).

    Raises
    ------
    MissingDataError
        If it is missing, or of another format, with the command that creates the dataset.
    CorruptDataError
        If it is not a JSON object, or any field differs from what was written.
    """
    data_dir = Path(data_dir)
    recover(data_dir)
    path = data_dir / MANIFEST
    if not path.is_file():
        raise MissingDataError(
            f"no demonstration data at '{data_dir}' ({MANIFEST} is missing). "
            f"Create it with: {GENERATE_COMMAND}"
        )
    try:
        manifest = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise _corrupt(data_dir, f"{MANIFEST} is not JSON ({e})") from None
    if not isinstance(manifest, dict):
        raise _corrupt(data_dir, f"{MANIFEST} is not a JSON object")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise MissingDataError(
            f"'{data_dir}' holds dataset format {manifest.get('format_version')}, this code "
            f"reads format {FORMAT_VERSION}; regenerate it with: {GENERATE_COMMAND}"
        )
    expected, actual = manifest.get(DIGEST), manifest_digest(manifest)
    if expected != actual:
        said = f"its {DIGEST} says {expected}" if expected else f"it has no {DIGEST}"
        raise _corrupt(data_dir, f"{MANIFEST}'s fields give {actual}, {said}")
    return manifest


def _read_manifest(data_dir: Path) -> dict[str, Any]:
    """The checked manifest, after checking that the trajectories exist and match it."""
    manifest = read_manifest(data_dir)
    if not (data_dir / TRAJECTORIES).is_file():
        raise MissingDataError(
            f"no demonstration data at '{data_dir}' ({TRAJECTORIES} is missing). "
            f"Create it with: {GENERATE_COMMAND}"
        )
    expected = (manifest.get("files") or {}).get(TRAJECTORIES)
    actual = "sha256:" + hashlib.sha256((data_dir / TRAJECTORIES).read_bytes()).hexdigest()
    if expected != actual:
        raise _corrupt(data_dir, f"{TRAJECTORIES} has {actual}, the manifest says {expected}")
    return manifest


def load_demos(data_dir: str | Path, verify: bool = True) -> tuple[DemoSet, dict[str, Any]]:
    """Read and verify the dataset; the manifest returned carries the recomputed ``content_hash``.

    Raises
    ------
    MissingDataError
        The directory, its manifest or its trajectories are missing (with the command).
    CorruptDataError
        The file's SHA-256, the table's shape or the content hash disagree with the manifest.
    """
    data_dir = Path(data_dir)
    manifest = _read_manifest(data_dir)
    tbl = pq.read_table(data_dir / TRAJECTORIES)
    B = int(manifest["n_trajectories"])
    N = int(manifest["steps_per_trajectory"])
    if tbl.num_rows != B * N:
        raise _corrupt(data_dir, f"{tbl.num_rows} rows, not {B} trajectories x {N} samples")
    col = lambda name: tbl.column(name).to_numpy()  # noqa: E731
    k, traj = col("k").reshape(B, N), col("traj").reshape(B, N)
    if not (np.all(k == np.arange(N)) and np.all(traj == np.arange(B)[:, None])):
        raise _corrupt(data_dir, "the rows are not whole trajectories in order")
    first = np.arange(B) * N
    x = np.stack([col(f"x{i}") for i in range(MAX_ORDER)], axis=-1).reshape(B, N, MAX_ORDER)
    demos = DemoSet(
        x=x,
        r=col("r").reshape(B, N),
        u=col("u").reshape(B, N),
        y=col("y").reshape(B, N),
        tag=col("tag")[first].astype(np.int64),
        order=col("order")[first].astype(np.int64),
        plant=np.asarray(tbl.column("plant").take(first).to_pylist()),
        amplitude=col("amplitude")[first],
        dt=float(manifest["dt"]),
        family=np.asarray(tbl.column("family").take(first).to_pylist()),
        variant=col("variant")[first].astype(np.int64) if "variant" in tbl.column_names else None,
    )
    if verify:
        computed = content_hash(demos, manifest.get("config", {}))
        if computed != manifest.get("content_hash"):
            raise _corrupt(
                data_dir,
                f"content hash {computed}, the manifest says {manifest.get('content_hash')}",
            )
        manifest["content_hash"] = computed  # what the arrays give, not what was read back
    return demos, manifest
