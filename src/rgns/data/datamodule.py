"""The LightningDataModule: a dataset folder in, PyG batches of windows out."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import lightning as L
import torch
from torch.utils.data import Sampler, Subset
from torch_geometric.loader import DataLoader

from rgns.data.contract import Contents, DatasetError, check_dataset, open_split
from rgns.data.stats import compute_statistics
from rgns.data.windows import StridedSplit, TrajectoryDataset, WindowDataset
from rgns.errors import ConfigError

log = logging.getLogger(__name__)


STRIDED_STATISTICS = ("vel_mean", "vel_std", "acc_mean", "acc_std")


def at_stride(metadata: dict, stride: int, statistics: dict | None = None) -> dict:
    """A dataset's metadata for every ``stride``-th frame of its trajectories: ``dt`` times the
    stride, ``stride``, ``sequence_length`` (frames - 1) of phase 0, and the velocity and
    acceleration ``statistics`` of the strided train split
    (:func:`~rgns.data.stats.compute_statistics` of a :class:`~rgns.data.windows.StridedSplit`),
    or, without them, no statistics at all: they do not follow from the stride-1 ones. The
    metadata itself at stride 1."""
    if stride == 1:
        return metadata
    strided = {key: value for key, value in metadata.items() if key not in STRIDED_STATISTICS}
    strided.update(statistics or {}, dt=metadata["dt"] * stride, stride=stride,
                   sequence_length=metadata["sequence_length"] // stride)
    return strided


class ResumableOrder(Sampler[int]):
    """``RandomSampler``'s order of the training windows, resumable within an epoch.

    Each epoch draws its seed from torch's global generator when iterated, as ``RandomSampler``
    does, so a run that is not resumed sees exactly the windows ``shuffle=True`` gives.
    :meth:`resume_at` makes the next epoch that seed's order from a position on: the rest of the
    epoch a checkpoint was saved in, instead of a new epoch's first windows again.
    """

    def __init__(self, size: int):
        self.size = size
        self.seed: int | None = None  # the epoch's, and where in its order it started, once iterated
        self.start = 0
        self._resume: tuple[int, int] | None = None

    def resume_at(self, seed: int, position: int) -> None:
        self._resume = (seed, position)

    def __iter__(self):
        seed, start = self._resume if self._resume is not None else (None, 0)
        self._resume = None
        if seed is None or start >= self.size:  # nothing to resume, or the epoch was done: a new one
            seed, start = int(torch.empty((), dtype=torch.int64).random_().item()), 0
        self.seed, self.start = seed, start
        order = torch.randperm(self.size, generator=torch.Generator().manual_seed(seed))
        yield from order[start:].tolist()

    def __len__(self) -> int:
        return self.size


class ResumableLoader(DataLoader):
    """The training loader, with the ``state_dict`` / ``load_state_dict`` Lightning saves in a
    checkpoint's loop state and restores on ``resume=``: where in its epoch's order the loader was
    (:class:`ResumableOrder`). The position counts the windows of the batches the loader handed
    out in the epoch; Lightning fetches none ahead from a loader of known length, so at a
    checkpoint they are the windows trained on.
    """

    def __init__(self, dataset, batch_size: int, **kwargs):
        self.order = ResumableOrder(len(dataset))
        super().__init__(dataset, batch_size=batch_size, sampler=self.order, **kwargs)
        self._handed_out = 0

    def __iter__(self):
        self._handed_out = 0
        for batch in super().__iter__():
            self._handed_out += 1
            yield batch

    def state_dict(self) -> dict:
        return {"seed": self.order.seed, "position": self.order.start + self._handed_out * self.batch_size}

    def load_state_dict(self, state: dict) -> None:
        self.order.resume_at(state["seed"], state["position"])


class ParticleDataModule(L.LightningDataModule):
    """Windows for training and validation, trajectories for rollouts.

    The whole dataset is checked (:func:`~rgns.data.contract.check_dataset`: metadata types and
    ranges, every split, every trajectory) once, before training starts: in :meth:`prepare_data`,
    or when :attr:`metadata` or :meth:`setup` is first reached.

    Args:
        root: the dataset folder (``metadata.json`` + ``{train,valid,test}.h5``).
        make: called as ``make(out_dir=root)`` by ``prepare_data`` when the folder has no
            ``metadata.json`` (e.g. a partial of :func:`rgns.data.generate.generate_dataset`);
            ``None`` means the dataset must already exist.
        make_root: the one folder ``make`` may generate into (the configured default dataset's);
            a missing ``root`` anywhere else is an error naming it, so a typo in ``data.root`` is
            never filled with a new dataset. ``None``: ``root`` itself.
        history: k, velocities per history.
        noise_std: random-walk noise on training windows.
        batch_size: graphs per batch (the paper's is 2).
        num_workers: DataLoader worker processes.
        lead, horizon: extra frames of each training window before and after it, for training
            through several steps (``module.pushforward``, ``module.unroll``; see
            :class:`~rgns.data.windows.WindowDataset`).
        early_windows: with a lead, also train on the windows fewer than ``lead`` frames into a
            trajectory (a pushforward from them starts at its first frame; see
            :class:`~rgns.data.windows.WindowDataset`).
        cache_mb: training trajectories kept in memory once read, per process (MiB; see
            :class:`~rgns.data.windows.WindowDataset`).
        position_correction, position_noise, noise_low: variants of the training noise (see
            :class:`~rgns.data.windows.WindowDataset`; 0, 1 and 1: GNS's).
        stride: k, train and validate on every k-th frame: one step of the model is k frames of
            the data. Each trajectory is cut into its k phases (frames ``r, r+k, r+2k, ...`` for
            ``r = 0 .. k-1``, :class:`~rgns.data.windows.StridedSplit`), so every frame is used and
            no window is thrown away; windows, validation rollouts and statistics are taken on
            those. :attr:`metadata` (what the model is built from, and its checkpoint records) is
            the strided data's: ``dt`` times k, ``stride: k``, ``sequence_length`` of phase 0, and
            ``vel_mean``/``vel_std``/``acc_mean``/``acc_std`` of the strided train split
            (velocities ``p^{t+k} - p^t``). Every phase must hold a training window; 1 (the default)
            is the data as it is.
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
        make_root: str | None = None,
        cache_mb: float = 1024.0,
        position_correction: float = 0.0,
        position_noise: float = 1.0,
        noise_low: float = 1.0,
        early_windows: bool = False,
        stride: int = 1,
    ):
        super().__init__()
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ConfigError(f"data.stride={stride!r}: must be an integer >= 1 (train on every k-th frame; "
                              "1: every frame)")
        if isinstance(history, bool) or not isinstance(history, int) or history < 1:
            raise ValueError(f"history={history!r}: a state needs at least one velocity (k >= 1; GNS uses 5)")
        if not noise_std >= 0:  # also refuses NaN
            raise ValueError(f"noise_std={noise_std!r}: the training noise's std must be >= 0 (0: no noise)")
        if batch_size < 1 or num_workers < 0:
            raise ValueError(f"data.batch_size={batch_size} must be >= 1 and data.num_workers={num_workers} >= 0")
        self.root = Path(root)
        self.make = make
        self.make_root = None if make_root is None else Path(make_root)
        self.history, self.noise_std = history, noise_std
        self.batch_size, self.num_workers = batch_size, num_workers
        self.lead, self.horizon, self.early_windows = lead, horizon, early_windows
        self.cache_mb = cache_mb
        self.position_correction, self.position_noise = position_correction, position_noise
        self.noise_low = noise_low
        self.stride = stride
        self._contents: Contents | None = None
        self._metadata: dict | None = None

    def prepare_data(self) -> None:
        if not (self.root / "metadata.json").is_file():
            self._make()
        self.check()

    def _make(self) -> None:
        how = (f"make one with `python -m rgns.data.generate scene=waterdrop out_dir={self.root}` or convert "
               f"DeepMind's files with `python -m rgns.data.convert SRC_DIR {self.root}`")
        if self.make is None:
            raise DatasetError(f"{self.root}: no dataset here (no metadata.json); {how}")
        if self.make_root is not None and self.make_root.resolve() != self.root.resolve():
            raise DatasetError(
                f"{self.root}: no dataset here (no metadata.json), and only the default dataset, {self.make_root}, is "
                f"generated on first use (data.make_root). Check data.root for a typo, or {how}"
            )
        self.make(out_dir=str(self.root))

    def check(self) -> Contents:
        """The whole dataset, checked once (see the class docs)."""
        if self._contents is None:
            k = self.history
            # a training window spans lead + k + 1 + horizon frames (early windows fill in the lead),
            # a validation window k + 2
            lead = 0 if self.early_windows else self.lead
            window = {"train": lead + k + 1 + self.horizon, "valid": k + 2}
            contents = check_dataset(self.root, min_frames=window)
            if not contents.shapes["train"]:
                raise DatasetError(f"{self.root / 'train.h5'}: no trajectories; nothing to train on")
            self._check_stride(contents, window)
            if not contents.shapes["valid"]:
                log.warning("%s: no trajectories: training runs without validation (no val/ metrics, no best "
                            "checkpoint)", self.root / "valid.h5")
            self._contents = contents
        return self._contents

    def _check_stride(self, contents: Contents, window: dict[str, int]) -> None:
        """Every phase of every trajectory at ``stride`` holds a window: its shortest phase has
        ``T // stride`` frames."""
        if self.stride == 1:
            return
        for split, frames_needed in window.items():
            for i, (frames, _, _) in enumerate(contents.shapes[split]):
                if frames // self.stride < frames_needed:
                    raise DatasetError(
                        f"{self.root / f'{split}.h5'}, trajectory {i:05d}: data.stride={self.stride} leaves "
                        f"{frames // self.stride} frames of its {frames} in its shortest phase, fewer than the "
                        f"{frames_needed} a {split} window needs; use a smaller data.stride (at most "
                        f"{max(frames // frames_needed, 1)}) or longer trajectories")

    @property
    def metadata(self) -> dict:
        """``metadata.json`` plus ``particle_types``, those of the train split: a model built from it
        (and its checkpoint) knows which types it was trained on. With a stride, the strided data's
        (see the class docs): ``dt``, ``stride``, ``sequence_length`` and the statistics."""
        if self._metadata is None:
            contents = self.check()
            metadata = dict(contents.metadata, particle_types=contents.particle_types["train"])
            if self.stride > 1:
                with open_split(self.root, "train") as train:
                    statistics = compute_statistics(StridedSplit(train, self.stride))
                metadata = at_stride(metadata, self.stride, statistics)
            self._metadata = metadata
        return dict(self._metadata)

    @property
    def radius(self) -> float:
        return float(self.metadata["default_connectivity_radius"])

    def split(self, name: str):
        """One split, every ``stride``-th frame (:class:`~rgns.data.windows.StridedSplit`) when strided."""
        split = open_split(self.root, name, min_frames=self.history + 2)
        return split if self.stride == 1 else StridedSplit(split, self.stride)

    def setup(self, stage: str | None = None) -> None:
        self.check()
        if stage in (None, "fit"):
            self.train_set = WindowDataset(self.split("train"), self.radius, self.history, self.noise_std,
                                           self.lead, self.horizon, self.cache_mb, self.position_correction,
                                           self.position_noise, self.noise_low, self.early_windows)
            self.valid_set = WindowDataset(self.split("valid"), self.radius, self.history, 0.0)
            self.valid_trajectories = TrajectoryDataset(self.split("valid"))

    def _loader(self, dataset, make: type[DataLoader] = DataLoader, **options) -> DataLoader:
        return make(dataset, batch_size=self.batch_size, num_workers=self.num_workers,
                    persistent_workers=self.num_workers > 0, **options)

    def train_dataloader(self) -> DataLoader:
        if self.trainer is not None and self.trainer.world_size > 1:
            # Lightning gives each rank its DistributedSampler share (resumed runs start the epoch's order again)
            return self._loader(self.train_set, shuffle=True)
        return self._loader(self.train_set, ResumableLoader)

    def val_dataloader(self) -> DataLoader:
        # the windows in one fixed shuffled order: validation on the first batches only
        # (trainer.limit_val_batches) then covers every trajectory and phase, not the first frames
        # of the first trajectory (on the default data: free fall alone)
        order = torch.randperm(len(self.valid_set), generator=torch.Generator().manual_seed(0)).tolist()
        return self._loader(Subset(self.valid_set, order), shuffle=False)

