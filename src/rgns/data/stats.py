"""Velocity and acceleration statistics of a split, streamed one trajectory at a time.

Units are metadata's: per frame (dt = 1), as DeepMind's ``vel_mean``/``vel_std``/``acc_mean``/``acc_std``.
Kinematic particles are left out: they are conditions, not dynamics.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

from rgns.data.contract import KINEMATIC, Trajectory


class RunningMoments:
    """Per-component mean and std over streamed rows (Chan's parallel update, float64)."""

    def __init__(self, dim: int):
        self.count = 0
        self.mean = np.zeros(dim)
        self.m2 = np.zeros(dim)

    def update(self, rows: np.ndarray) -> None:
        rows = np.asarray(rows, dtype=np.float64).reshape(-1, self.mean.shape[0])
        if len(rows) == 0:
            return
        n, mean = len(rows), rows.mean(0)
        m2 = ((rows - mean) ** 2).sum(0)
        total = self.count + n
        delta = mean - self.mean
        self.mean = self.mean + delta * n / total
        self.m2 = self.m2 + m2 + delta**2 * self.count * n / total
        self.count = total

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.m2 / max(self.count, 1))


def compute_statistics(trajectories: Iterable[Trajectory | tuple]) -> dict[str, list[float]]:
    """Return ``vel_mean``, ``vel_std``, ``acc_mean``, ``acc_std`` over the non-kinematic particles."""
    velocity = acceleration = None
    for position, particle_type in trajectories:
        position = np.asarray(position, dtype=np.float64)[:, np.asarray(particle_type) != KINEMATIC]
        if velocity is None:
            velocity, acceleration = RunningMoments(position.shape[-1]), RunningMoments(position.shape[-1])
        vel = np.diff(position, axis=0)
        velocity.update(vel)
        acceleration.update(np.diff(vel, axis=0))
    if velocity is None or velocity.count == 0:
        raise ValueError("cannot compute statistics: no trajectory with moving particles")
    return {
        "vel_mean": velocity.mean.tolist(),
        "vel_std": velocity.std.tolist(),
        "acc_mean": acceleration.mean.tolist(),
        "acc_std": acceleration.std.tolist(),
    }
