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


# ---------------------------------------------------------------- the regime of a dataset
def mean_neighbours(position, radius: float) -> float:
    """Mean number of other particles within ``radius`` of a particle, ``[M, D]`` positions:
    the fluid's density as the graph sees it (0 for no particles)."""
    from scipy.spatial import cKDTree

    position = np.asarray(position, dtype=np.float64)
    if len(position) == 0:
        return 0.0
    pairs = cKDTree(position).query_pairs(radius, output_type="ndarray")
    return 2 * len(pairs) / len(position)


def regime(position: np.ndarray, particle_type: np.ndarray, radius: float, points: int = 10) -> dict:
    """Is the fluid coherent, and does it settle? For one trajectory ``[T, N, D]``:

    - ``neighbours``: mean number of other moving particles within ``radius`` of a moving
      particle, at ``points`` frames spread evenly over the trajectory (WaterDrop's pools hold
      ~9-12 once settled; films one particle thick ~5-6);
    - ``energy_left``: mean kinetic energy of the last 10 frames over its peak (per-frame
      velocities: the fraction of the motion still there at the end).
    """
    moving = np.asarray(position, dtype=np.float64)[:, np.asarray(particle_type) != KINEMATIC]  # [T, M, D]
    frames = np.linspace(0, len(moving) - 1, points).round().astype(int)
    neighbours = [mean_neighbours(moving[frame], radius) for frame in frames]
    energy = (np.diff(moving, axis=0) ** 2).sum(-1).mean(-1)  # [T - 1]
    peak = float(energy.max())
    return {"frames": frames.tolist(), "neighbours": neighbours,
            "energy_left": float(energy[-10:].mean() / peak) if peak > 0 else 0.0}


def dataset_regime(trajectories: Iterable[Trajectory | tuple], radius: float, points: int = 10) -> dict:
    """:func:`regime` over a split: per trajectory, and the summary figures ``neighbours_mean``
    (at each of the ``points`` frames, over trajectories), ``settled_neighbours_min`` (the least
    mean neighbours of any trajectory over its second half) and ``energy_left_max``."""
    per_trajectory = [regime(p, t, radius, points) for p, t in trajectories]
    if not per_trajectory:
        raise ValueError("no trajectories")
    neighbours = np.array([r["neighbours"] for r in per_trajectory])  # [n, points]
    return {
        "neighbours_mean": neighbours.mean(0).round(2).tolist(),
        "settled_neighbours_min": float(neighbours[:, points // 2:].mean(1).min().round(2)),
        "energy_left_max": float(max(r["energy_left"] for r in per_trajectory)),
        "trajectories": per_trajectory,
    }


def regime_summary(trajectories: Iterable[Trajectory | tuple], radius: float, points: int = 10) -> dict:
    """:func:`dataset_regime`'s summary figures without the per-trajectory rows: what a dataset's
    ``metadata.json`` records as ``regime`` (``python -m rgns.data.stats DIR`` prints the rows)."""
    summary = dataset_regime(trajectories, radius, points)
    summary.pop("trajectories")
    return summary


def main(argv=None) -> dict:
    """``python -m rgns.data.stats DATASET_DIR [--split train] [--points 10]``: print the regime."""
    import argparse
    import json

    from rgns.data.contract import open_split, read_metadata

    parser = argparse.ArgumentParser(prog="python -m rgns.data.stats", description=main.__doc__)
    parser.add_argument("root", help="a dataset folder (metadata.json + {train,valid,test}.h5)")
    parser.add_argument("--split", default="train")
    parser.add_argument("--points", type=int, default=10, help="frames per trajectory at which neighbours are counted")
    parser.add_argument("--json", action="store_true", help="print the whole result as JSON")
    args = parser.parse_args(argv)
    radius = float(read_metadata(args.root)["default_connectivity_radius"])
    with open_split(args.root, args.split) as data:
        result = dataset_regime(data, radius, args.points)
    if args.json:
        print(json.dumps(result, indent=1))
        return result
    print(f"{args.root} [{args.split}], {len(result['trajectories'])} trajectories, radius {radius:g}")
    print("mean neighbours at frames", result["trajectories"][0]["frames"], "(of the first; the same fractions for all):")
    print("  " + ", ".join(f"{n:.1f}" for n in result["neighbours_mean"]))
    print(f"least mean neighbours of a trajectory over its second half: {result['settled_neighbours_min']:.1f}")
    energy = [r["energy_left"] for r in result["trajectories"]]
    print(f"kinetic energy of the last 10 frames over its peak: {100 * min(energy):.1f}% .. {100 * max(energy):.1f}%")
    return result


if __name__ == "__main__":
    main()
