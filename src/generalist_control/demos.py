"""The demonstration dataset on disk: ``trajectories.parquet`` plus ``manifest.json``.

Trajectories are stored one row per sample (long form); windows are cut at load time by
:func:`generalist_control.windows.build_windows`, and the manifest counts them. Writes go
to a temporary directory that is renamed into place, so an interrupted run never leaves a
half-written dataset.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from generalist_control.paths import GENERATE_COMMAND
from generalist_control.plants import MAX_ORDER
from generalist_control.windows import Windows, build_windows, integral_of_error

__all__ = [
    "DemoSet",
    "MissingDataError",
    "content_hash",
    "load_demos",
    "write_demos",
]

TRAJECTORIES = "trajectories.parquet"
MANIFEST = "manifest.json"
FORMAT_VERSION = 1


class MissingDataError(FileNotFoundError):
    """The demonstration dataset is missing or incomplete."""


@dataclass(frozen=True)
class DemoSet:
    """``B`` trajectories of ``N`` samples each, in deviation coordinates.

    Attributes
    ----------
    x : ndarray, shape (B, N, MAX_ORDER)
        Zero-padded states at each sample.
    r, u, y : ndarray, shape (B, N)
    tag, order : ndarray of int, shape (B,)
    plant : ndarray of str, shape (B,)
    amplitude : ndarray, shape (B,)
        Step amplitude of each trajectory (after the plant's amplitude scale).
    dt : float
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

    def windows(self, history: int, horizon: int, integral: bool = False) -> Windows:
        """All training windows of the set.

        With ``integral``, the error integral is the last state channel (see
        :func:`~generalist_control.windows.integral_of_error`).
        """
        z = integral_of_error(self.r, self.y, self.dt) if integral else None
        return build_windows(self.x, self.r, self.u, self.tag, self.order, history, horizon, z)


def content_hash(demos: DemoSet, config: dict[str, Any]) -> str:
    """SHA-256 over the arrays' bytes and the canonical JSON of the data config."""
    h = hashlib.sha256()
    for a in (demos.x, demos.r, demos.u, demos.y, demos.amplitude):
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    for a in (demos.tag, demos.order):
        h.update(np.ascontiguousarray(a, dtype="<i8").tobytes())
    h.update("\0".join(demos.plant.tolist()).encode())
    h.update(json.dumps(config, sort_keys=True, separators=(",", ":")).encode())
    return "sha256:" + h.hexdigest()


def _to_table(demos: DemoSet) -> pa.Table:
    B, N = demos.r.shape
    rep = lambda a: np.repeat(a, N)  # noqa: E731
    cols: dict[str, Any] = {
        "traj": rep(np.arange(B, dtype=np.int32)),
        "plant": pa.array(rep(demos.plant)).dictionary_encode(),
        "tag": rep(demos.tag.astype(np.int16)),
        "order": rep(demos.order.astype(np.int8)),
        "amplitude": rep(demos.amplitude),
        "k": np.tile(np.arange(N, dtype=np.int32), B),
        "t": np.tile(np.arange(N) * demos.dt, B),
    }
    for i in range(MAX_ORDER):
        cols[f"x{i}"] = demos.x[:, :, i].ravel()
    cols.update(r=demos.r.ravel(), u=demos.u.ravel(), y=demos.y.ravel())
    return pa.table(cols)


def write_demos(out_dir: str | Path, demos: DemoSet, manifest: dict[str, Any]) -> Path:
    """Write the dataset atomically to ``out_dir`` (replacing any previous one)."""
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        pq.write_table(_to_table(demos), tmp / TRAJECTORIES, compression="zstd")
        digest = hashlib.sha256((tmp / TRAJECTORIES).read_bytes()).hexdigest()
        manifest = {**manifest, "files": {TRAJECTORIES: "sha256:" + digest}}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
        os.chmod(tmp, 0o755)
        old = None
        if out_dir.exists():
            old = out_dir.with_name(f".{out_dir.name}.old-{os.getpid()}")
            os.replace(out_dir, old)
        os.replace(tmp, out_dir)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def load_demos(data_dir: str | Path) -> tuple[DemoSet, dict[str, Any]]:
    """Read the dataset written by the ``generate`` stage.

    Raises
    ------
    MissingDataError
        If the directory, its manifest or its trajectories are missing, with the command
        that creates them.
    """
    data_dir = Path(data_dir)
    for name in (MANIFEST, TRAJECTORIES):
        if not (data_dir / name).is_file():
            raise MissingDataError(
                f"no demonstration data at '{data_dir}' ({name} is missing). "
                f"Create it with: {GENERATE_COMMAND}"
            )
    manifest = json.loads((data_dir / MANIFEST).read_text())
    if manifest.get("format_version") != FORMAT_VERSION:
        raise MissingDataError(
            f"'{data_dir}' holds dataset format {manifest.get('format_version')}, this code "
            f"reads format {FORMAT_VERSION}; regenerate it with: {GENERATE_COMMAND}"
        )
    tbl = pq.read_table(data_dir / TRAJECTORIES)
    B = int(manifest["n_trajectories"])
    N = int(manifest["steps_per_trajectory"])
    col = lambda name: tbl.column(name).to_numpy()  # noqa: E731
    first = np.arange(B) * N
    x = np.stack([col(f"x{i}") for i in range(MAX_ORDER)], axis=-1).reshape(B, N, MAX_ORDER)
    demos = DemoSet(
        x=x,
        r=col("r").reshape(B, N),
        u=col("u").reshape(B, N),
        y=col("y").reshape(B, N),
        tag=col("tag")[first].astype(np.int64),
        order=col("order")[first].astype(np.int64),
        plant=np.asarray(tbl.column("plant").to_pylist())[first],
        amplitude=col("amplitude")[first],
        dt=float(manifest["dt"]),
    )
    return demos, manifest
