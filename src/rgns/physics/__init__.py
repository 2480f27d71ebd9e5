"""Ground-truth particle solvers written in Taichi.

- :class:`MPMSolver` (``rgns.physics.mpm``): MLS-MPM in 2D and 3D for weakly compressible water
  and Drucker-Prager sand, walls at the box bounds and static capsule obstacles (ramps) as grid
  boundary conditions. The family of DeepMind's WaterDrop, WaterRamps and Sand data.
- :class:`SPHSolver` (``rgns.physics.sph``): weakly compressible SPH (Tait equation of state,
  Adami-style wall particles) in 2D and 3D, differentiable through Taichi autodiff with one
  checkpoint per frame; the solver the optimisation baseline differentiates.

Both share one interface: ``rollout(position [N, D], velocity [N, D], material [N], num_frames)``
returns positions ``[num_frames, N, D]`` (frame 0 is the initial state), in metres and seconds.

Taichi is initialised once per process, on first use, by :func:`init_taichi` (CPU, one thread by
default); importing this package has no side effects.
"""
from rgns.physics.geometry import Capsule
from rgns.physics.runtime import init_taichi

__all__ = ["Capsule", "MPMSolver", "SPHSolver", "init_taichi"]


def __getattr__(name):  # solvers import Taichi lazily
    if name == "MPMSolver":
        from rgns.physics.mpm import MPMSolver

        return MPMSolver
    if name == "SPHSolver":
        from rgns.physics.sph import SPHSolver

        return SPHSolver
    raise AttributeError(name)
