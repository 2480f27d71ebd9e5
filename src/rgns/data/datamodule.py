"""The LightningDataModule: a dataset folder in, PyG batches of windows out."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import lightning as L
from torch_geometric.loader import DataLoader

from rgns.data.contract import DatasetError, open_split, read_metadata
from rgns.data.windows import TrajectoryDataset, WindowDataset


class ParticleDataModule(L.LightningDataModule):
    """Windows for training and validation, trajectories for rollouts.

    Args:
        root: the dataset folder (``metadata.json`` + ``{train,valid,test}.h5``).
        make: called as ``make(out_dir=root)`` by ``prepare_data`` when the folder has no
            ``metadata.json`` (e.g. a partial of :func:`rgns.data.generate.generate_dataset`);
            ``None`` means the dataset must already exist.
        history: k, velocities per history.
        noise_std: random-walk noise on training windows.
        batch_size: graphs per batch (the paper's is 2).
        num_workers: DataLoader worker processes.
        lead, horizon: extra frames of each training window before and after it, for training
            through several steps (``module.pushforward``, ``module.unroll``; see
            :class:`~rgns.data.windows.WindowDataset`).
    """

    def __init__(
        self,
        root: str,
        make: Callable[[str], None] | None = None,
        history: int = 5,
        noise_std: float = 6.7e-4,
        batch_size: int = 2,
        num_workers: int = 0,
        lead: int = 0,
        horizon: int = 1,
    ):
        super().__init__()
        self.root = Path(root)
        self.make = make
        self.history, self.noise_std = history, noise_std
        self.batch_size, self.num_workers = batch_size, num_workers
        self.lead, self.horizon = lead, horizon
        self._metadata: dict | None = None

    def prepare_data(self) -> None:
        if (self.root / "metadata.json").is_file():
            return
        if self.make is None:
            raise DatasetError(
                f"{self.root}: no dataset here. Make one with "
                f"`python -m rgns.data.generate scene=waterdrop out_dir={self.root}` or convert "
                f"DeepMind's files with `python -m rgns.data.convert SRC_DIR {self.root}`"
            )
        self.make(out_dir=str(self.root))

    @property
    def metadata(self) -> dict:
        if self._metadata is None:
            self._metadata = read_metadata(self.root)
        return self._metadata

    @property
    def radius(self) -> float:
        return float(self.metadata["default_connectivity_radius"])

    def split(self, name: str):
        return open_split(self.root, name, min_frames=self.history + 2)

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit"):
            self.train_set = WindowDataset(self.split("train"), self.radius, self.history, self.noise_std,
                                           self.lead, self.horizon)
            self.valid_set = WindowDataset(self.split("valid"), self.radius, self.history, 0.0)
            self.valid_trajectories = TrajectoryDataset(self.split("valid"))

    def _loader(self, dataset, shuffle: bool) -> DataLoader:
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            shuffle=shuffle,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.valid_set, shuffle=False)

