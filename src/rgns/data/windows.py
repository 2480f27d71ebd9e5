"""Training windows and whole trajectories, as PyG data.

A window of trajectory ``s`` at frame ``t`` holds k + 2 frames ``p^{t-k} ... p^{t+1}``, that is
k + 1 velocities ``v^{t-k+1} ... v^{t+1}``. It yields both samples of the step t <-> t+1 on the
one graph they share, the radius graph of ``p^t``:

- forward:  history ``V^t = (v^{t-k+1} ... v^t)``    -> newest velocity ``v^{t+1}``;
- inverse:  history ``V^{t+1} = (v^{t-k+2} ... v^{t+1})`` -> oldest velocity ``v^{t-k+1}``.

Training noise is GNS's random walk: velocity noise accumulated over the window (zero on
kinematic particles), the oldest frame ``p^{t-k}`` left clean. As in GNS (Sanchez-Gonzalez et
al. 2020, DeepMind's ``learned_simulator``), the targets are the clean velocities ``v^{t+1}``
(forward) and ``v^{t-k+1}`` (inverse): the predicted change cancels the noise of the input
velocities, not the drift of the noisy positions, which the network cannot observe. (Making
the step land on the true position instead asks the network to undo the accumulated position
noise, several times ``noise_std``, from velocities that do not reveal it.)
"""
from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset
from torch_geometric.data import Data

from rgns.data.contract import KINEMATIC, Split, Trajectory
from rgns.data.graph import radius_graph


def random_walk_noise(shape: tuple[int, int, int], noise_std: float, moving: torch.Tensor,
                      level: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Velocity noise accumulated over the window; the last velocity's noise has std
    ``noise_std`` times ``level`` (a number, or one per particle: e.g. each graph's level of a batch).

    Shapes:
        shape: ``(W, N, D)`` velocities per window; moving: ``[N]`` bool; level: ``[N]`` or a
        number  ->  ``[W, N, D]``
    """
    steps = torch.randn(shape) * (noise_std / shape[0] ** 0.5)
    return steps.cumsum(0) * (moving * torch.as_tensor(level))[None, :, None]


def noise_level(low: float, size: int | None = None) -> torch.Tensor | float:
    """A window's noise level, uniform in ``[low, 1]`` (``low = 1``: always 1, GNS's fixed noise;
    ``low = 0``: from clean to the full ``noise_std``); ``size`` levels for a batch of windows."""
    if low >= 1:
        return 1.0
    u = torch.rand(() if size is None else (size,))
    return low + (1 - low) * u


def scale_position_noise(noisy: torch.Tensor, clean: torch.Tensor, scale: float) -> torch.Tensor:
    """A noisy position with its noise scaled: ``clean + scale (noisy - clean)`` (``noisy`` itself
    at 1, so GNS's path is untouched).  ``[N, D]``"""
    return noisy if scale == 1 else clean + scale * (noisy - clean)


class WindowDataset(Dataset):
    """Every (trajectory, t) window of a split, as a PyG ``Data`` with the fields

    ``pos [N, D]`` (``p~^t``), ``edge_index [2, E]``, ``particle_type [N]``,
    ``forward_input [N, k, D]``, ``forward_target [N, D]``,
    ``inverse_input [N, k, D]``, ``inverse_target [N, D]``.

    With ``lead > 0`` or ``horizon > 1`` (training through several steps: pushforward, unrolled
    losses) it also holds ``frames [N, lead + k + 1 + horizon, D]``, the clean positions
    ``p^{t-k-lead} .. p^{t+horizon}``, and ``t`` runs only where they all exist. With
    ``early_windows`` as well, ``t`` runs from ``k`` as without a lead: a window fewer than
    ``lead`` frames into its trajectory repeats the first frame in place of the missing ones, and
    its ``lead_frames [N]`` (``min(lead, t - k)``, the real frames before ``p^{t-k}``) tells a
    pushforward how far back it may start.

    Args:
        split: an open :class:`~rgns.data.contract.Split` (or its :class:`StridedSplit`).
        radius: connectivity radius.
        history: k, the number of velocities in a history.
        noise_std: GNS random-walk noise std (0 for validation).
        lead: frames before ``p^{t-k}`` a pushforward may start from.
        early_windows: keep the windows with fewer than ``lead`` frames before ``p^{t-k}`` (their
            pushforward starts at the trajectory's first frame, so it pushes fewer steps); without
            it a lead drops the first ``lead`` targets of every trajectory from training.
        horizon: frames after ``p^t`` an unrolled loss may reach (1: the next frame only).
        position_correction: the fraction of ``p~^t``'s noise the forward target takes back (the
            next position lands that much nearer the clean ``p^{t+1}``; 0: GNS's target).
        position_noise: the input position's share of the noise, scaled (1: GNS's ``p~^t``; 0: the
            clean ``p^t`` with the noisy velocities).
        noise_low: each window's noise std is ``noise_std`` times a level drawn uniformly in
            ``[noise_low, 1]`` (1: GNS's fixed level). Rollouts feed the network its own, nearly
            clean histories; with a fixed level it never sees one in training.
        cache_mb: trajectories kept in memory once read, up to this many MiB (per process: each
            DataLoader worker has its own); past it, only the last one read. Shuffled windows
            jump between trajectories, and reading one from the file costs more than building
            the window (the default dataset's 40 MB train split is read once).
    """

    def __init__(self, split: Split, radius: float, history: int = 5, noise_std: float = 0.0,
                 lead: int = 0, horizon: int = 1, cache_mb: float = 1024.0, position_correction: float = 0.0,
                 position_noise: float = 1.0, noise_low: float = 1.0, early_windows: bool = False):
        if not 0 <= noise_low <= 1:
            raise ValueError(f"noise_low={noise_low!r} must be in [0, 1] (1: every window at noise_std)")
        if lead < 0 or horizon < 1:
            raise ValueError(f"lead={lead} must be >= 0 and horizon={horizon} >= 1")
        self.split, self.radius, self.history, self.noise_std = split, radius, history, noise_std
        self.lead, self.horizon, self.early_windows = lead, horizon, early_windows
        self.position_correction, self.position_noise = position_correction, position_noise
        self.noise_low = noise_low
        self.cache_bytes = int(cache_mb * 2**20)
        self._kept: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        self._kept_bytes = 0
        self.window = history + 2
        # window (s, t) covers frames t-k-lead .. t+horizon; t runs over k+lead .. T-1-horizon
        # (from k with early windows, the missing lead frames filled in)
        first = history if early_windows else history + lead
        self.index = [(s, t) for s, (frames, _, _) in enumerate(split.shapes)
                      for t in range(first, frames - horizon)]
        self._cache: tuple[int, torch.Tensor, torch.Tensor] | None = None

    def __len__(self) -> int:
        return len(self.index)

    def _trajectory(self, s: int) -> tuple[torch.Tensor, torch.Tensor]:
        if s in self._kept:
            return self._kept[s]
        if self._cache is None or self._cache[0] != s:
            position, particle_type = self.split[s]
            self._cache = (s, torch.from_numpy(position), torch.from_numpy(particle_type))
            size = position.nbytes + particle_type.nbytes
            if self._kept_bytes + size <= self.cache_bytes:
                self._kept[s] = self._cache[1:]
                self._kept_bytes += size
        return self._cache[1], self._cache[2]

    def __getitem__(self, i: int) -> Data:
        s, t = self.index[i]
        position, particle_type = self._trajectory(s)
        k = self.history
        frames = position[t - k : t + 2]  # [k+2, N, D]: p^{t-k} .. p^{t+1}
        velocity = frames[1:] - frames[:-1]  # [k+1, N, D]: v^{t-k+1} .. v^{t+1}
        if self.noise_std > 0:
            level = noise_level(self.noise_low)
            noisy = velocity + random_walk_noise(velocity.shape, self.noise_std, particle_type != KINEMATIC, level)
        else:
            noisy = velocity
        noisy_position = frames[0] + noisy.cumsum(0)  # [k+1, N, D]: p~^{t-k+1} .. p~^{t+1}
        position_t = scale_position_noise(noisy_position[-2], frames[-2], self.position_noise)  # p~^t
        forward_target = velocity[-1]  # the clean v^{t+1}
        if self.position_correction:  # and back towards the clean p^{t+1} by this fraction of p~^t's noise
            forward_target = forward_target - self.position_correction * (position_t - frames[-2])
        inverse_target = velocity[0]  # the clean v^{t-k+1}
        extra = {}
        if self.lead > 0 or self.horizon > 1:
            begin = t - k - self.lead
            frames = position[max(begin, 0) : t + 1 + self.horizon]
            if begin < 0:  # an early window: the first frame stands in for the -begin missing ones
                frames = torch.cat([position[:1].expand(-begin, *position.shape[1:]), frames])
            extra["frames"] = frames.transpose(0, 1).contiguous()
            if self.early_windows:
                extra["lead_frames"] = torch.full((len(particle_type),), min(self.lead, t - k), dtype=torch.long)
        return Data(
            **extra,
            pos=position_t,
            edge_index=radius_graph(position_t, self.radius),
            particle_type=particle_type,
            forward_input=noisy[:-1].transpose(0, 1).contiguous(),  # [N, k, D]
            forward_target=forward_target,
            inverse_input=noisy[1:].transpose(0, 1).contiguous(),  # [N, k, D]
            inverse_target=inverse_target,
            num_nodes=len(particle_type),
        )


class StridedSplit:
    """Every ``stride``-th frame of each trajectory of a split, one trajectory per phase: the
    trajectory ``p^0, p^1, ...`` of ``T`` frames becomes ``p^r, p^{r+k}, p^{r+2k}, ...`` for each
    phase ``r = 0 .. k-1``, so every frame is in one of them and no window of the data is thrown
    away. Read like a :class:`~rgns.data.contract.Split` (``shapes``, ``len``, indexing,
    iteration) by :class:`WindowDataset`, :class:`TrajectoryDataset` and
    :func:`~rgns.data.stats.compute_statistics`. Trajectories are ordered phase first
    (``index = phase * len(split) + trajectory``), so the first few are phase 0 of different
    trajectories. A stride of 1 is the split itself, in its order.

    Shapes:
        one trajectory: ``[T, N, D]``  ->  its phase ``r``: ``[len(range(r, T, k)), N, D]``
    """

    def __init__(self, split: Split, stride: int):
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ValueError(f"stride={stride!r}: every k-th frame needs an integer k >= 1")
        self.split, self.stride = split, stride
        self.shapes = [(len(range(phase, frames, stride)), particles, dim)
                       for phase in range(stride) for frames, particles, dim in split.shapes]

    def __len__(self) -> int:
        return len(self.shapes)

    def __getitem__(self, index: int) -> Trajectory:
        phase, s = divmod(index, len(self.split))
        position, particle_type = self.split[s]
        return Trajectory(np.ascontiguousarray(position[phase :: self.stride]), particle_type)

    def __iter__(self):
        return (self[i] for i in range(len(self)))


class TrajectoryDataset(Dataset):
    """Whole trajectories for rollouts: ``Data(position [T, N, D], particle_type [N])``."""

    def __init__(self, split: Split | StridedSplit):
        self.split = split

    def __len__(self) -> int:
        return len(self.split)

    def __getitem__(self, i: int) -> Data:
        position, particle_type = self.split[i]
        return Data(position=torch.from_numpy(position), particle_type=torch.from_numpy(particle_type))

