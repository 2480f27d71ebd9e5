"""Validation of the water solvers against experiment and hydrostatics; makes the figures of
``docs/validation.md``::

    python -m rgns.physics.validation [--out docs/figures]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from rgns.physics.materials import WATER
from rgns.physics.geometry import lattice

G = 9.81
# Martin & Moyce (1952), Phil. Trans. R. Soc. A 244:312: surge front Z = x/a against T = t sqrt(2g/a)
MARTIN_MOYCE = np.array([(0.83, 1.22), (1.22, 1.47), (2.00, 2.29), (2.55, 3.00), (3.35, 4.13),
                         (4.03, 4.94), (4.42, 5.88), (5.09, 6.98)])


def surge_front(position: np.ndarray, left_wall: float, width: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(T, Z) of a dam-break trajectory ``[T, N, D]``: the front is the rightmost particle."""
    T = np.arange(len(position)) * dt * np.sqrt(2 * G / width)
    Z = (position[:, :, 0].max(1) - left_wall) / width
    return T, Z


def dam_break_errors(T: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """Relative error of Z against Martin & Moyce at their measurements with T in [1, 3]."""
    measured = MARTIN_MOYCE[(MARTIN_MOYCE[:, 0] >= 1) & (MARTIN_MOYCE[:, 0] <= 3)]
    return np.interp(measured[:, 0], T, Z) / measured[:, 1] - 1


def dam_break(solver, width: float, spacing: float, num_frames: int = 140) -> tuple[np.ndarray, np.ndarray]:
    """Run a 2D dam break (column ``width`` x ``2 width`` at the lower-left corner); returns (T, Z)."""
    lower = np.array([solver.lower[0], solver.lower[1]])
    column = lattice(lower, lower + [width, 2 * width], spacing)
    trajectory = solver.rollout(column, np.zeros_like(column), np.full(len(column), WATER), num_frames)
    return surge_front(trajectory, lower[0], width, solver.frame_dt)


def resting_tank(solver, depth: float, spacing: float, num_frames: int = 401, hydrostatic: bool = True):
    """Run a 2D tank of water ``depth`` deep across the box; returns positions ``[T, N, 2]``."""
    lower, upper = np.array(solver.lower[:2]), np.array(solver.upper[:2])
    tank = lattice(lower, np.array([upper[0], lower[1] + depth]), spacing)
    pressure = 1000.0 * G * (lower[1] + depth - tank[:, 1]) if hydrostatic else None
    kwargs = {"pressure": pressure} if pressure is not None else {}
    return solver.rollout(tank, np.zeros_like(tank), np.full(len(tank), WATER), num_frames, **kwargs)


def hydrostatic_profile(position: np.ndarray, pressure: np.ndarray, spacing: float, bins: int = 6
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Mean depth and mean pressure in ``bins`` equal layers of a settled tank ``position [N, D]``
    (y is axis 1); the free surface is half a spacing above the highest particle."""
    depth = position[:, 1].max() + 0.5 * spacing - position[:, 1]
    layer = np.minimum((depth / depth.max() * bins).astype(int), bins - 1)
    mean_depth = np.array([depth[layer == b].mean() for b in range(bins)])
    mean_pressure = np.array([pressure[layer == b].mean() for b in range(bins)])
    return mean_depth, mean_pressure


def main(argv: list[str] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rgns.physics.mpm import MPMSolver

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="docs/figures")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    solvers = {"MLS-MPM": MPMSolver(dim=2, capacity=8192)}
    try:
        from rgns.physics.sph import SPHSolver

        solvers["WCSPH"] = SPHSolver(dim=2, capacity=8192)
    except ImportError:
        pass

    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.plot(*MARTIN_MOYCE.T, "ko", label="Martin & Moyce 1952")
    ax.fill_between(MARTIN_MOYCE[:, 0], 0.8 * MARTIN_MOYCE[:, 1], 1.2 * MARTIN_MOYCE[:, 1], color="0.85",
                    label="±20%")
    for name, solver in solvers.items():
        T, Z = dam_break(solver, width=0.156, spacing=0.0065, num_frames=200)
        errors = dam_break_errors(T, Z)
        print(f"dam break {name}: relative error at T in [1, 3]: {np.round(errors, 3).tolist()}")
        ax.plot(T, Z, label=f"{name} (max error {np.abs(errors).max():.0%})")
    ax.set(xlabel="T = t sqrt(2g/a)", ylabel="Z = x/a", xlim=(0, 3.5), ylim=(1, 5))
    ax.axvspan(1, 3, color="C2", alpha=0.07)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "validation_dambreak.png", dpi=120)

    fig, (ax, ax_p) = plt.subplots(1, 2, figsize=(9, 3.6))
    depth, num_frames = 0.12, 801
    for name, solver in solvers.items():
        # MPM starts with its hydrostatic pressure; SPH (whose density is a sum over the particles)
        # from an uncompressed lattice, so it first settles
        spacing = getattr(solver, "spacing", 0.008)
        trajectory = resting_tank(solver, depth=depth, spacing=spacing, num_frames=num_frames,
                                  hydrostatic=name == "MLS-MPM")
        speed = np.linalg.norm(np.diff(trajectory, axis=0), axis=-1).max(1) / solver.frame_dt
        t = np.arange(1, len(trajectory)) * solver.frame_dt
        print(f"resting tank {name}: max speed over the last 0.1 s {speed[-40:].max():.2e} m/s "
              f"(bound {0.01 * np.sqrt(G * depth):.2e})")
        ax.semilogy(t, speed, label=name)
        if hasattr(solver, "pressures"):
            T, P = hydrostatic_profile(trajectory[-1], solver.pressures(), spacing)
            print(f"resting tank {name}: mean depth (m) {np.round(T, 4).tolist()}, mean pressure / (rho0 g depth) "
                  f"{np.round(P / (1000.0 * G * T), 3).tolist()}")
            ax_p.plot(T, P, "o-", color=ax.lines[-1].get_color(), label=f"{name} (layer means at t = 2 s)")
    ax.axhline(0.01 * np.sqrt(G * depth), color="k", ls="--", label="1% of sqrt(g depth)")
    ax.set(xlabel="t (s)", ylabel="max particle speed (m/s)")
    ax.legend(fontsize=8)
    line = np.linspace(0, depth, 2)
    ax_p.plot(line, 1000.0 * G * line, "k--", label="rho0 g depth")
    ax_p.fill_between(line, 0.9 * 1000.0 * G * line, 1.1 * 1000.0 * G * line, color="0.85", label="±10%")
    ax_p.set(xlabel="depth below the free surface (m)", ylabel="pressure (Pa)")
    ax_p.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "validation_tank.png", dpi=120)


if __name__ == "__main__":
    main()
