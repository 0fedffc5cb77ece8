"""Training and validation windows of ``data/demos``, split by trajectory, held in memory.

Batches are whole index batches (shuffled from ``seed + epoch``: a resume sees the same
order) gathered from a few tensors: no per-sample ``__getitem__``, no workers.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, Sampler

from generalist_control.data.demos import MissingDataError, load_demos
from generalist_control.data.windows import Windows
from generalist_control.training.family_set import FamilySet
from generalist_control.training.settings import LoaderSettings

__all__ = [
    "BatchIndexSampler",
    "DemoDataModule",
    "MissingPlantError",
    "WindowTensors",
    "split_by_trajectory",
]

FIELDS = ("state", "mask", "ref", "tag", "target")


def split_by_trajectory(plant: np.ndarray, val_fraction: float, seed: int) -> np.ndarray:
    """Validation flags of trajectories of the plants ``plant`` names, stratified by plant.

    ``val_fraction`` of each plant's go to validation, at least one of a plant with two or more.
    """
    rng = np.random.default_rng(seed)
    is_val = np.zeros(len(plant), dtype=bool)
    if val_fraction == 0.0:
        return is_val
    for name in np.unique(plant):
        idx = np.flatnonzero(plant == name)
        n_val = min(len(idx) - 1, max(1, round(val_fraction * len(idx))))
        is_val[rng.permutation(idx)[:n_val]] = True
    return is_val


class MissingPlantError(MissingDataError):
    """A plant of the config's set (``systems``) that the dataset does not hold."""


class WindowTensors(Dataset):
    """Window tensors indexed a whole batch at a time: ``ds[idx]`` -> dict of tensors."""

    def __init__(self, windows: Windows, keep: np.ndarray | None = None) -> None:
        sel = slice(None) if keep is None else np.flatnonzero(keep)
        self.tensors: dict[str, Tensor] = {
            k: torch.from_numpy(np.ascontiguousarray(getattr(windows, k)[sel])) for k in FIELDS
        }

    def __len__(self) -> int:
        return self.tensors["tag"].shape[0]

    def append(self, windows: Windows) -> None:
        """Add windows (e.g. DAgger's); a dataloader built afterwards sees them."""
        for k in FIELDS:
            extra = torch.from_numpy(np.ascontiguousarray(getattr(windows, k)))
            self.tensors[k] = torch.cat([self.tensors[k], extra.to(self.tensors[k].dtype)])

    def __getitem__(self, idx: Tensor) -> dict[str, Tensor]:
        # index_select: the same rows as v[idx], faster
        return {k: v.index_select(0, idx) for k, v in self.tensors.items()}


class BatchIndexSampler(Sampler[Tensor]):
    """Index batches over ``n`` items, reshuffled each epoch from ``seed + epoch``."""

    def __init__(self, n: int, batch_size: int, shuffle: bool, seed: int = 0) -> None:
        self.n, self.batch_size, self.shuffle, self.seed = n, batch_size, shuffle, seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Called by Lightning at the start of every training epoch."""
        self.epoch = epoch

    def __len__(self) -> int:
        return math.ceil(self.n / self.batch_size)

    def __iter__(self) -> Iterator[Tensor]:
        if self.shuffle:
            g = torch.Generator().manual_seed(self.seed + self.epoch)
            order = torch.randperm(self.n, generator=g)
        else:
            order = torch.arange(self.n)
        yield from order.split(self.batch_size)


class DemoDataModule(L.LightningDataModule):
    """Windows of the dataset at ``data_dir`` for Lightning (``tags``, ``orders`` after setup).

    ``seed`` seeds the split and the shuffling; ``plants``: only these (None: all; the split is
    made over the whole dataset first); ``families`` join the dataset (list their plants too).
    """

    def __init__(
        self,
        data_dir: str | Path,
        history: int,
        horizon: int,
        loader: LoaderSettings,
        seed: int = 0,
        plants: Sequence[str] | None = None,
        channels: Sequence[str] = (),
        families: FamilySet | None = None,
    ) -> None:
        super().__init__()
        self.families = families
        self.data_dir = Path(data_dir)
        self.integral = "integral" in channels
        self.controls = "previous_control" in channels
        self.history, self.horizon = int(history), int(horizon)
        self.loader, self.seed = loader, int(seed)
        self.plants = [str(p) for p in plants] if plants else None
        self.manifest: dict[str, Any] = {}
        self.tags: dict[str, int] = {}
        self.orders: dict[str, int] = {}
        self.dt = float("nan")
        self.train_set: WindowTensors | None = None
        self.val_set: WindowTensors | None = None

    def setup(self, stage: str | None = None) -> None:
        """Load the data and split it (once).

        Raises
        ------
        generalist_control.data.demos.MissingDataError
            No dataset at ``data_dir``, or (:class:`MissingPlantError`) not one of ``plants``.
        """
        if self.train_set is not None:
            return
        demos, self.manifest = load_demos(self.data_dir)
        if self.families is not None:  # their plants after the catalogue's (train_families)
            demos, self.manifest = self.families.joined(demos, self.manifest)
        kept_traj = self._kept(demos.plant)
        windows = demos.windows(self.history, self.horizon, self.integral, self.controls)
        is_val = split_by_trajectory(demos.plant, self.loader.val_fraction, self.seed)[
            windows.traj
        ]
        kept = kept_traj[windows.traj]
        self.train_set = WindowTensors(windows, kept & ~is_val)
        self.val_set = WindowTensors(windows, kept & is_val)
        rows = zip(demos.plant.tolist(), demos.tag, demos.order, kept_traj, strict=True)
        kept_rows = [(str(p), int(t), int(n)) for p, t, n, kept in rows if kept]
        self.tags = {p: t for p, t, _ in kept_rows}
        self.orders = {p: n for p, _, n in kept_rows}
        self.dt = float(demos.dt)

    def _kept(self, plant: np.ndarray) -> np.ndarray:
        """Trajectories of :attr:`plants` (all without), after checking the data has them."""
        if self.plants is None:
            return np.ones(len(plant), dtype=bool)
        held = sorted(set(plant.tolist()))
        missing = [p for p in self.plants if p not in held]
        if missing:
            raise MissingPlantError(
                f"the plant set (systems) names {missing}, but the dataset at {self.data_dir} "
                f"holds only {held}: generate one that holds them (python -m "
                "generalist_control.generate with the same systems and "
                f"paths.data_dir={self.data_dir}), or train on the plants it holds "
                f"(systems.include=[{','.join(held)}])"
            )
        return np.isin(plant, self.plants)

    def meta(self) -> dict[str, Any]:
        """Plain-typed facts a trained policy needs to be traced and deployed."""
        return {
            "tags": dict(self.tags),
            "orders": dict(self.orders),
            "dt": self.dt,
            "history": self.history,
            "horizon": self.horizon,
            "content_hash": str(self.manifest.get("content_hash", "")),
            "data_dir": str(self.data_dir),
            "n_train": len(self.train_set or ()),
            "n_val": len(self.val_set or ()),
        }

    def split(self, name: str) -> WindowTensors:
        """The ``train`` or ``val`` windows (an error before :meth:`setup`)."""
        windows = self.train_set if name == "train" else self.val_set
        if windows is None:
            raise RuntimeError("DemoDataModule: call setup() before asking for its windows")
        return windows

    def train_dataloader(self) -> DataLoader:
        """Shuffled index batches over the training windows."""
        train_set = self.split("train")
        sampler = BatchIndexSampler(len(train_set), self.loader.batch_size, True, self.seed)
        return DataLoader(train_set, sampler=sampler, batch_size=None)

    def val_dataloader(self) -> DataLoader:
        """Validation windows in order."""
        val_set = self.split("val")
        sampler = BatchIndexSampler(len(val_set), self.loader.val_batch_size, False)
        return DataLoader(val_set, sampler=sampler, batch_size=None)
