"""Weakly compressible SPH (WCSPH) in 2D and 3D, differentiable with one checkpoint per frame.

- density by summation over fluid and wall particles, Tait equation of state
  ``p = B ((rho / rho0)^7 - 1)`` clamped at 0 (no tension at the free surface),
  ``B = rho0 c^2 / 7``; cubic-spline kernel, smoothing length ``1.2 * spacing``;
- momentum: symmetric pressure gradient, Monaghan's artificial viscosity, gravity;
  symplectic Euler;
- walls: three layers of fixed wall particles outside the box, at the fluid's spacing; they add
  to the density and push back with the fluid particle's own (mirrored) pressure (Akinci et al.
  2012), free slip. A particle that still crosses a wall is put back on it.

Gradients (reverse mode, Taichi autodiff) of the final positions and velocities with respect to
the initial ones: :meth:`SPHSolver.forward` keeps one checkpoint (positions, velocities) per frame
on the host; :meth:`SPHSolver.backward` replays each frame from its checkpoint, newest first, and
back-propagates through its substeps. Device memory is one frame's substeps
(``substeps x N``); host memory ``2 x frames x N x D`` floats.
"""
# no `from __future__ import annotations`: Taichi reads kernel annotations at runtime

import math
from typing import Sequence

import numpy as np
import taichi as ti

from rgns.data.contract import WATER
from rgns.physics.runtime import ensure_taichi


def wall_particles(bounds: np.ndarray, spacing: float, layers: int) -> np.ndarray:
    """``layers`` lattice layers of particles just outside the box ``bounds`` ``[D, 2]``: ``[M, D]``."""
    lower, upper = bounds[:, 0], bounds[:, 1]
    counts = np.round((upper - lower) / spacing).astype(int) + 2 * layers
    index = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, len(counts))
    points = lower - (layers - 0.5) * spacing + index * spacing
    outside = ((points < lower) | (points > upper)).any(-1)
    return points[outside]


@ti.data_oriented
class SPHSolver:
    """WCSPH, differentiable.

    Args:
        dim: 2 or 3.
        capacity: the most fluid particles.
        bounds: ``[[lo, hi]] * dim``, the walls.
        spacing: particle spacing at rest (m); sets the particle mass and the kernel size.
        frame_dt: seconds between frames; substeps: solver steps per frame.
        gravity: ``[dim]`` m/s^2.
        density: rest density; sound_speed: c (m/s), ~10x the largest flow speed.
        viscosity: Monaghan's alpha.
        max_neighbours: neighbour slots per particle.
        dtype: ``"f32"`` or ``"f64"`` (f64 for finite-difference checks).
    """

    def __init__(self, dim: int = 2, capacity: int = 4096,
                 bounds: Sequence[Sequence[float]] = ((0.1, 0.9), (0.1, 0.9)), spacing: float = 0.0065,
                 frame_dt: float = 0.0025, substeps: int = 25, gravity: Sequence[float] = (0.0, -9.81),
                 density: float = 1000.0, sound_speed: float = 25.0, viscosity: float = 0.05,
                 max_neighbours: int | None = None, dtype: str = "f32"):
        ensure_taichi()
        bounds = np.asarray(bounds, dtype=float)
        if dim not in (2, 3) or bounds.shape != (dim, 2) or len(gravity) != dim:
            raise ValueError(f"bounds {bounds.shape} and gravity {len(gravity)} must match dim={dim}")
        self.dim, self.capacity, self.spacing = dim, capacity, spacing
        self.frame_dt, self.substeps, self.dt = frame_dt, substeps, frame_dt / substeps
        self.lower, self.upper = tuple(bounds[:, 0].tolist()), tuple(bounds[:, 1].tolist())
        self.gravity = tuple(float(g) for g in gravity)
        self.rho0, self.sound_speed, self.alpha = density, sound_speed, viscosity
        self.B = density * sound_speed**2 / 7.0
        self.h = 1.2 * spacing  # smoothing length; the kernel reaches 2h
        self.support = 2.0 * self.h
        self.mass = density * spacing**dim
        self.sigma = 10.0 / (7.0 * math.pi * self.h**2) if dim == 2 else 1.0 / (math.pi * self.h**3)
        self.max_neighbours = max_neighbours or (64 if dim == 2 else 160)

        walls = wall_particles(bounds, spacing, layers=int(math.ceil(self.support / spacing)))
        self.num_walls = len(walls)
        real = ti.f64 if dtype == "f64" else ti.f32
        self.real = real
        vec = ti.types.vector(dim, real)
        S = substeps
        self.x = ti.field(vec, (S + 1, capacity), needs_grad=True)  # positions within one frame
        self.v = ti.field(vec, (S + 1, capacity), needs_grad=True)
        self.rho = ti.field(real, (S, capacity), needs_grad=True)
        self.p = ti.field(real, (S, capacity), needs_grad=True)
        self.wall = ti.field(vec, max(self.num_walls, 1))
        self.wall.from_numpy(walls.astype(np.float64 if dtype == "f64" else np.float32))
        self.neighbours = ti.field(ti.i32, (S, capacity, self.max_neighbours))  # >= capacity: wall
        self.num_neighbours = ti.field(ti.i32, (S, capacity))
        self.overflow = ti.field(ti.i32, ())
        self.num_particles = ti.field(ti.i32, ())
        # uniform cell grid of side `support` over the box and its walls
        margin = (math.ceil(self.support / spacing) + 1) * spacing
        self.cell_origin = tuple((bounds[:, 0] - margin).tolist())
        self.cell_shape = tuple(int(math.ceil((e + 2 * margin) / self.support)) + 1
                                for e in bounds[:, 1] - bounds[:, 0])
        self.cell_capacity = 32 if dim == 2 else 96
        self.cell_count = ti.field(ti.i32, self.cell_shape)
        self.cell_items = ti.field(ti.i32, (*self.cell_shape, self.cell_capacity))
        self._checkpoints: list[tuple[np.ndarray, np.ndarray]] = []

    # ------------------------------------------------------------------ kernel function
    @ti.func
    def W(self, r):
        """Cubic spline, branch-free: sigma/4 ((2 - q)_+^3 - 4 (1 - q)_+^3), q = r / h."""
        q = r / self.h
        return 0.25 * self.sigma * (ti.max(2.0 - q, 0.0) ** 3 - 4.0 * ti.max(1.0 - q, 0.0) ** 3)

    @ti.func
    def dW(self, r):
        """dW/dr."""
        q = r / self.h
        return -0.75 * self.sigma / self.h * (ti.max(2.0 - q, 0.0) ** 2 - 4.0 * ti.max(1.0 - q, 0.0) ** 2)

    @ti.func
    def cell_of(self, pos):
        return ti.cast((pos - ti.Vector(self.cell_origin)) / self.support, ti.i32)

    @ti.func
    def position(self, s, k):
        """Position of particle k at substep s: fluid below capacity, wall above."""
        result = ti.Vector.zero(self.real, self.dim)
        if k < self.capacity:
            result = self.x[s, k]
        else:
            result = self.wall[k - self.capacity]
        return result

    # ------------------------------------------------------------------ neighbours (not differentiated)
    @ti.kernel
    def find_neighbours(self, s: ti.i32):
        for I in ti.grouped(self.cell_count):
            self.cell_count[I] = 0
        for k in range(self.num_particles[None] + self.num_walls):
            index = k if k < self.num_particles[None] else self.capacity + k - self.num_particles[None]
            cell = self.cell_of(self.position(s, index))
            slot = ti.atomic_add(self.cell_count[cell], 1)
            if slot < self.cell_capacity:
                self.cell_items[cell, slot] = index
            else:
                self.overflow[None] = 1
        for i in range(self.num_particles[None]):
            xi = self.x[s, i]
            cell = self.cell_of(xi)
            count = 0
            for offset in ti.static(ti.grouped(ti.ndrange(*((-1, 2),) * self.dim))):
                c = cell + offset
                for slot in range(ti.min(self.cell_count[c], self.cell_capacity)):
                    k = self.cell_items[c, slot]
                    if k != i and (xi - self.position(s, k)).norm() < self.support:
                        if count < self.max_neighbours:
                            self.neighbours[s, i, count] = k
                            count += 1
                        else:
                            self.overflow[None] = 1
            self.num_neighbours[s, i] = count

    @ti.kernel
    def clear_fields(self):
        for s, i in self.rho:
            self.rho[s, i] = 0.0

    # ------------------------------------------------------------------ differentiable substep
    @ti.kernel
    def density(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            self.rho[s, i] += self.mass * self.sigma  # the particle itself: W(0) = sigma
            for n in range(self.num_neighbours[s, i]):
                k = self.neighbours[s, i, n]
                r = self.x[s, i] - self.position(s, k)
                distance = ti.max(r.norm(), 1e-9 * self.h)
                self.rho[s, i] += self.mass * self.W(distance)

    @ti.kernel
    def pressure(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            self.p[s, i] = self.B * ti.max((self.rho[s, i] / self.rho0) ** 7 - 1.0, 0.0)

    @ti.kernel
    def gravity_step(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            self.v[s + 1, i] = self.v[s, i] + self.dt * ti.Vector(self.gravity, self.real)

    @ti.kernel
    def forces(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            pi_term = self.p[s, i] / self.rho[s, i] ** 2
            for n in range(self.num_neighbours[s, i]):
                k = self.neighbours[s, i, n]
                r = self.x[s, i] - self.position(s, k)
                distance = ti.max(r.norm(), 1e-9 * self.h)
                grad_W = self.dW(distance) * r / distance  # [D]
                if k < self.capacity:  # fluid: pressure and artificial viscosity
                    v_ij = self.v[s, i] - self.v[s, k]
                    mu = self.h * ti.min(v_ij.dot(r), 0.0) / (distance**2 + 0.01 * self.h**2)
                    rho_mean = 0.5 * (self.rho[s, i] + self.rho[s, k])
                    viscous = -self.alpha * self.sound_speed * mu / rho_mean
                    pk_term = self.p[s, k] / self.rho[s, k] ** 2
                    self.v[s + 1, i] += -self.dt * self.mass * (pi_term + pk_term + viscous) * grad_W
                else:  # wall: mirrored pressure
                    self.v[s + 1, i] += -self.dt * self.mass * 2.0 * pi_term * grad_W

    @ti.kernel
    def advect(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            x_new = self.x[s, i] + self.dt * self.v[s + 1, i]
            for d in ti.static(range(self.dim)):
                x_new[d] = ti.min(ti.max(x_new[d], self.lower[d]), self.upper[d])
            self.x[s + 1, i] = x_new

    @ti.kernel
    def carry_over(self):
        """The last substep of a frame is the first of the next."""
        for i in range(self.num_particles[None]):
            self.x[0, i] = self.x[self.substeps, i]
            self.v[0, i] = self.v[self.substeps, i]

    def _frame(self) -> None:
        self.clear_fields()
        for s in range(self.substeps):
            self.find_neighbours(s)
            self.density(s)
            self.pressure(s)
            self.gravity_step(s)
            self.forces(s)
            self.advect(s)
        if self.overflow[None]:
            raise RuntimeError("SPH neighbour or cell slots overflowed: raise max_neighbours / cell_capacity")

    def _frame_backward(self) -> None:
        for s in reversed(range(self.substeps)):
            self.advect.grad(s)
            self.forces.grad(s)
            self.gravity_step.grad(s)
            self.pressure.grad(s)
            self.density.grad(s)

    # ------------------------------------------------------------------ python side
    def _load(self, position: np.ndarray, velocity: np.ndarray) -> None:
        n = len(position)
        if n > self.capacity:
            raise ValueError(f"{n} particles exceed the solver's capacity {self.capacity}")
        np_real = np.float64 if self.real == ti.f64 else np.float32
        x = np.zeros((self.substeps + 1, self.capacity, self.dim), np_real)
        v = np.zeros_like(x)
        x[0, :n], v[0, :n] = position, velocity
        self.x.from_numpy(x)
        self.v.from_numpy(v)
        self.num_particles[None] = n
        self.overflow[None] = 0

    def _state(self, s: int = 0) -> tuple[np.ndarray, np.ndarray]:
        n = self.num_particles[None]
        return self.x.to_numpy()[s, :n].copy(), self.v.to_numpy()[s, :n].copy()

    def rollout(self, position: np.ndarray, velocity: np.ndarray, material: np.ndarray | None = None,
                num_frames: int = 2, obstacles: Sequence = ()) -> np.ndarray:
        """Simulate ``num_frames - 1`` frames; returns positions ``[num_frames, N, D]`` float32."""
        if obstacles:
            raise NotImplementedError("SPH scenes have walls only")
        if material is not None and not (np.asarray(material) == WATER).all():
            raise ValueError("SPH simulates water (type 5) only")
        self._load(position, velocity)
        trajectory = np.empty((num_frames, len(position), self.dim), np.float32)
        trajectory[0] = position
        for frame in range(1, num_frames):
            self._frame()
            self.carry_over()
            trajectory[frame] = self.x.to_numpy()[0, : len(position)]
        if not np.isfinite(trajectory).all():
            raise FloatingPointError("SPH rollout produced NaN or Inf; raise substeps")
        return trajectory

    def forward(self, position: np.ndarray, velocity: np.ndarray, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
        """Advance ``num_frames`` frames from ``position``, ``velocity`` ``[N, D]``, keeping one
        checkpoint per frame for :meth:`backward`. Returns the final positions and velocities."""
        self._load(position, velocity)
        self._checkpoints = []
        for _ in range(num_frames):
            self._checkpoints.append(self._state(0))
            self._frame()
            self.carry_over()
        return self._state(0)

    def backward(self, grad_position: np.ndarray, grad_velocity: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Vector-Jacobian product of the last :meth:`forward`: given dL/d(final position) (and
        optionally dL/d(final velocity)) ``[N, D]``, return dL/d(initial position), dL/d(initial
        velocity) ``[N, D]``."""
        if not self._checkpoints:
            raise RuntimeError("call forward() before backward()")
        grad_x = np.asarray(grad_position, dtype=float)
        grad_v = np.zeros_like(grad_x) if grad_velocity is None else np.asarray(grad_velocity, dtype=float)
        n = len(grad_x)
        np_real = np.float64 if self.real == ti.f64 else np.float32
        for position, velocity in reversed(self._checkpoints):
            self._load(position, velocity)
            self._frame()  # replay the frame from its checkpoint
            for field in (self.x, self.v):
                field.grad.fill(0)
            for field in (self.rho, self.p):
                field.grad.fill(0)
            seed_x = np.zeros((self.substeps + 1, self.capacity, self.dim), np_real)
            seed_v = np.zeros_like(seed_x)
            seed_x[self.substeps, :n], seed_v[self.substeps, :n] = grad_x, grad_v
            self.x.grad.from_numpy(seed_x)
            self.v.grad.from_numpy(seed_v)
            self._frame_backward()
            grad_x = self.x.grad.to_numpy()[0, :n].astype(float)
            grad_v = self.v.grad.to_numpy()[0, :n].astype(float)
        return grad_x, grad_v
