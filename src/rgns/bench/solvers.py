"""Ground-truth solver speed: ``python -m rgns.bench solvers [--seconds S] [--skip-dataset]``.

Prints simulated seconds per wall second for each solver at ~1k particles in 2D and ~5k in 3D
(Taichi compilation excluded), the time to generate the main job's default dataset
(``waterdrop``) and an estimate for the full WaterDrop-scale preset (``waterdrop_full``).
"""
import argparse
import tempfile
import time

import numpy as np

from rgns.data.contract import WATER
from rgns.data.scenes import lattice


def speed(solver, position: np.ndarray, seconds: float) -> float:
    """Simulated seconds per wall second of a falling block (after one warm-up frame)."""
    velocity = np.zeros_like(position)
    material = np.full(len(position), WATER)
    solver.rollout(position, velocity, material, 2)  # compile
    frames = max(int(round(seconds / solver.frame_dt)), 2)
    start = time.perf_counter()
    solver.rollout(position, velocity, material, frames + 1)
    return frames * solver.frame_dt / (time.perf_counter() - start)


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, default=0.25, help="simulated seconds per measurement")
    parser.add_argument("--skip-dataset", action="store_true")
    args = parser.parse_args(argv)

    from rgns.physics.mpm import MPMSolver
    from rgns.physics.sph import SPHSolver

    block_2d = lattice(np.array([0.3, 0.3]), np.array([0.3 + 32 * 0.0065, 0.3 + 32 * 0.0065]), 0.0065)  # 1024
    bounds_3d = [[0.1, 0.9]] * 3
    block_3d = lattice(np.array([0.3] * 3), np.array([0.3 + 17 * 0.015] * 3), 0.015)  # 4913
    cases = {
        f"MLS-MPM 2D, {len(block_2d)} particles": (lambda: MPMSolver(dim=2, capacity=len(block_2d)), block_2d),
        f"MLS-MPM 3D, {len(block_3d)} particles": (lambda: MPMSolver(dim=3, capacity=len(block_3d), n_grid=48,
                                                                     bounds=bounds_3d, gravity=(0, -9.81, 0)),
                                                   block_3d),
        f"WCSPH 2D, {len(block_2d)} particles": (lambda: SPHSolver(dim=2, capacity=len(block_2d)), block_2d),
        f"WCSPH 3D, {len(block_3d)} particles": (lambda: SPHSolver(dim=3, capacity=len(block_3d), spacing=0.015,
                                                                   bounds=bounds_3d, gravity=(0, -9.81, 0),
                                                                   substeps=10), block_3d),
    }
    for name, (make, position) in cases.items():
        print(f"{name}: {speed(make(), position, args.seconds):.3f} simulated s per wall s", flush=True)

    if not args.skip_dataset:
        from rgns.data.generate import generate_dataset, scene_config

        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            generate_dataset("waterdrop", f"{tmp}/small", workers=2, progress=False)
            print(f"default dataset (waterdrop, 2 workers): {time.perf_counter() - start:.1f} s")
            full = scene_config("waterdrop_full")
            full["splits"] = {"train": 4, "valid": 0, "test": 0}
            start = time.perf_counter()
            generate_dataset(full, f"{tmp}/full", workers=2, progress=False)
            per_trajectory = (time.perf_counter() - start) / 4
            total = sum(scene_config("waterdrop_full")["splits"].values())
            print(f"waterdrop_full: {per_trajectory:.1f} s per trajectory with 2 workers (incl. start-up) "
                  f"-> ~{per_trajectory * total / 60:.0f} min for {total} trajectories")
