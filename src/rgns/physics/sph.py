"""Weakly compressible SPH (WCSPH) in 2D and 3D, differentiable with one checkpoint per frame.

- density by summation over fluid and wall particles, Tait equation of state
  ``p = B ((rho / rho0)^7 - 1)`` clamped at 0 (no tension at the free surface),
  ``B = rho0 c^2 / 7``; cubic-spline kernel, smoothing length ``1.2 * spacing``; the particle mass
  is ``rho0`` over the kernel sum of the rest lattice, so a lattice at rest has density ``rho0``
  exactly (the cubic spline sums to 1.0008 / spacing^3 in 3D: 0.6% of B as a spurious pressure);
- momentum: symmetric pressure gradient, Monaghan's artificial viscosity, gravity;
  symplectic Euler;
- walls: layers of fixed wall particles outside the box, at the fluid's spacing, as deep as the
  kernel reaches. They add to the fluid's density and carry the pressure extrapolated from
  the fluid around them, hydrostatic term included (Adami, Hu & Adams 2012, eq. 27):
  ``p_w = (sum_f p_f W_wf + g . sum_f rho_f (x_w - x_f) W_wf) / sum_f W_wf`` and the density of
  that pressure by the equation of state; free slip. A particle that still crosses a wall is put
  back on it.

Gradients (reverse mode, Taichi autodiff) of the final positions and velocities with respect to
the initial ones::

    xK, vK = solver.forward(x0, v0, K)          # [N, D] each, keeps one checkpoint per frame
    gx0, gv0 = solver.backward(dL_dxK, dL_dvK)  # dL_dvK may be None

:meth:`SPHSolver.forward` keeps one checkpoint (positions, velocities) per frame on the host;
:meth:`SPHSolver.backward` replays each frame from its checkpoint, newest first, and
back-propagates through its substeps (kernel gradients in the reverse order of the forward
calls). Device memory is one frame's substeps (``substeps x N``); host memory
``2 x frames x N x D`` floats. The neighbour lists are built outside the differentiated kernels
and held constant (the kernel and its derivative vanish at the edge of its support, so a pair
entering or leaving a list changes nothing to first order).

In ``dtype="f64"`` every constant is cast to f64 in the kernels (a bare Python float in a Taichi
kernel is an f32 literal), so finite differences agree with the gradients to ~1e-8 (tested).
"""
# no `from __future__ import annotations`: Taichi reads kernel annotations at runtime

import math
from typing import Sequence

import numpy as np
import taichi as ti

from rgns.physics.materials import WATER
from rgns.physics.runtime import ensure_taichi


def wall_particles(bounds: np.ndarray, spacing: float, layers: int) -> np.ndarray:
    """``layers`` lattice layers of particles just outside the box ``bounds`` ``[D, 2]``: ``[M, D]``."""
    lower, upper = bounds[:, 0], bounds[:, 1]
    counts = np.round((upper - lower) / spacing).astype(int) + 2 * layers
    index = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, len(counts))
    points = lower - (layers - 0.5) * spacing + index * spacing
    outside = ((points < lower) | (points > upper)).any(-1)
    return points[outside]


def cubic_spline(r: np.ndarray, h: float, dim: int) -> np.ndarray:
    """The cubic-spline kernel ``W(r)`` of smoothing length ``h`` (numpy; the kernels' twin)."""
    sigma = 10.0 / (7.0 * math.pi * h**2) if dim == 2 else 1.0 / (math.pi * h**3)
    q = r / h
    return 0.25 * sigma * (np.maximum(2.0 - q, 0.0) ** 3 - 4.0 * np.maximum(1.0 - q, 0.0) ** 3)


def lattice_kernel_sum(spacing: float, h: float, dim: int) -> float:
    """``sum_j W(|x_j|)`` over an infinite square lattice of ``spacing`` (the rest density / mass)."""
    reach = int(math.ceil(2 * h / spacing))
    offsets = np.stack(np.meshgrid(*[np.arange(-reach, reach + 1)] * dim, indexing="ij"), -1).reshape(-1, dim)
    return float(cubic_spline(np.linalg.norm(offsets * spacing, axis=-1), h, dim).sum())


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
        max_neighbours: neighbour slots per particle (fluid and wall each).
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
        self.sigma = 10.0 / (7.0 * math.pi * self.h**2) if dim == 2 else 1.0 / (math.pi * self.h**3)
        self.mass = density / lattice_kernel_sum(spacing, self.h, dim)  # a rest lattice has density rho0
        self.max_neighbours = max_neighbours or (64 if dim == 2 else 160)

        walls = wall_particles(bounds, spacing, layers=int(math.ceil(self.support / spacing)))
        self.num_walls = len(walls)
        real = ti.f64 if dtype == "f64" else ti.f32
        self.real = real
        self.np_real = np.float64 if dtype == "f64" else np.float32
        vec = ti.types.vector(dim, real)
        S, M = substeps, max(self.num_walls, 1)
        self.x = ti.field(vec, (S + 1, capacity), needs_grad=True)  # positions within one frame
        self.v = ti.field(vec, (S + 1, capacity), needs_grad=True)
        self.rho = ti.field(real, (S, capacity), needs_grad=True)
        self.p = ti.field(real, (S, capacity), needs_grad=True)
        self.wall = ti.field(vec, M)
        self.wall.from_numpy(walls.astype(self.np_real))
        # Adami's extrapolation: numerator and denominator, then the wall's pressure and density
        self.wall_sum_p = ti.field(real, (S, M), needs_grad=True)
        self.wall_sum_W = ti.field(real, (S, M), needs_grad=True)
        self.wall_p = ti.field(real, (S, M), needs_grad=True)
        self.wall_rho = ti.field(real, (S, M), needs_grad=True)
        self.neighbours = ti.field(ti.i32, (S, capacity, self.max_neighbours))  # fluid indices
        self.num_neighbours = ti.field(ti.i32, (S, capacity))
        self.wall_neighbours = ti.field(ti.i32, (S, capacity, self.max_neighbours))  # wall indices
        self.num_wall_neighbours = ti.field(ti.i32, (S, capacity))
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
        q = r / self.real(self.h)
        return self.real(0.25 * self.sigma) * (ti.max(2.0 - q, 0.0) ** 3 - 4.0 * ti.max(1.0 - q, 0.0) ** 3)

    @ti.func
    def dW(self, r):
        """dW/dr."""
        q = r / self.real(self.h)
        return self.real(-0.75 * self.sigma / self.h) * (ti.max(2.0 - q, 0.0) ** 2 - 4.0 * ti.max(1.0 - q, 0.0) ** 2)

    @ti.func
    def cell_of(self, pos):
        return ti.cast((pos - ti.Vector(self.cell_origin)) / self.support, ti.i32)

    @ti.func
    def distance(self, r):
        return ti.max(r.norm(), self.real(1e-9 * self.h))

    # ------------------------------------------------------------------ neighbours (not differentiated)
    @ti.kernel
    def find_neighbours(self, s: ti.i32):
        """Neighbour lists of substep ``s``: fluid (``neighbours``) and wall (``wall_neighbours``)."""
        for I in ti.grouped(self.cell_count):
            self.cell_count[I] = 0
        for k in range(self.num_particles[None] + self.num_walls):
            pos = self.wall[0]
            index = k  # fluid 0..n-1; wall capacity + j
            if k < self.num_particles[None]:
                pos = self.x[s, k]
            else:
                pos = self.wall[k - self.num_particles[None]]
                index = self.capacity + k - self.num_particles[None]
            cell = self.cell_of(pos)
            slot = ti.atomic_add(self.cell_count[cell], 1)
            if slot < self.cell_capacity:
                self.cell_items[cell, slot] = index
            else:
                self.overflow[None] = 1
        for i in range(self.num_particles[None]):
            xi = self.x[s, i]
            cell = self.cell_of(xi)
            count, wall_count = 0, 0
            for offset in ti.static(ti.grouped(ti.ndrange(*((-1, 2),) * self.dim))):
                c = cell + offset
                for slot in range(ti.min(self.cell_count[c], self.cell_capacity)):
                    k = self.cell_items[c, slot]
                    if k < self.capacity:
                        if k != i and (xi - self.x[s, k]).norm() < self.support:
                            if count < self.max_neighbours:
                                self.neighbours[s, i, count] = k
                                count += 1
                            else:
                                self.overflow[None] = 1
                    elif (xi - self.wall[k - self.capacity]).norm() < self.support:
                        if wall_count < self.max_neighbours:
                            self.wall_neighbours[s, i, wall_count] = k - self.capacity
                            wall_count += 1
                        else:
                            self.overflow[None] = 1
            self.num_neighbours[s, i] = count
            self.num_wall_neighbours[s, i] = wall_count

    @ti.kernel
    def clear_fields(self):
        """Start values of the accumulated fields. A particle's own share of its density, m W(0),
        is a constant: it is set here, outside the differentiated kernels."""
        for s, i in self.rho:
            self.rho[s, i] = self.real(self.mass * self.sigma)
        for s, w in self.wall_p:
            self.wall_sum_p[s, w] = 0.0
            self.wall_sum_W[s, w] = 0.0
            self.wall_p[s, w] = 0.0
            self.wall_rho[s, w] = self.real(self.rho0)

    # ------------------------------------------------------------------ differentiable substep
    # Taichi 1.7's reverse mode gets a neighbour sum wrong (by 10-40%, measured) when the sum is
    # carried in a local variable across the dynamic neighbour loop, or when the same field
    # element is also written before that loop in the same kernel (the compiler turns it into
    # such a local). So every neighbour sum below adds straight into a global field inside the
    # innermost loop, one kernel per sum, with no branch that chooses what to read.
    @ti.kernel
    def density_fluid(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            for n in range(self.num_neighbours[s, i]):
                r = self.x[s, i] - self.x[s, self.neighbours[s, i, n]]
                self.rho[s, i] += self.real(self.mass) * self.W(self.distance(r))

    @ti.kernel
    def density_wall(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            for n in range(self.num_wall_neighbours[s, i]):
                r = self.x[s, i] - self.wall[self.wall_neighbours[s, i, n]]
                self.rho[s, i] += self.real(self.mass) * self.W(self.distance(r))

    @ti.kernel
    def pressure(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            self.p[s, i] = self.real(self.B) * ti.max((self.rho[s, i] / self.real(self.rho0)) ** 7 - 1.0, 0.0)

    @ti.kernel
    def wall_sums(self, s: ti.i32):
        """Adami's sums over the fluid around each wall particle, scattered from the fluid side."""
        for i in range(self.num_particles[None]):
            for n in range(self.num_wall_neighbours[s, i]):
                g = ti.Vector(self.gravity, self.real)
                w = self.wall_neighbours[s, i, n]
                r = self.wall[w] - self.x[s, i]  # wall minus fluid
                weight = self.W(self.distance(r))
                self.wall_sum_p[s, w] += (self.p[s, i] + self.rho[s, i] * g.dot(r)) * weight
                self.wall_sum_W[s, w] += weight

    @ti.kernel
    def wall_state(self, s: ti.i32):
        for w in range(self.num_walls):
            if self.wall_sum_W[s, w] > 0.0:
                pressure = ti.max(self.wall_sum_p[s, w] / self.wall_sum_W[s, w], 0.0)
                self.wall_p[s, w] = pressure  # (a field written here is never read back here)
                self.wall_rho[s, w] = self.real(self.rho0) * (pressure / self.real(self.B) + 1.0) ** self.real(1.0 / 7.0)

    @ti.kernel
    def gravity_step(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            self.v[s + 1, i] = self.v[s, i] + self.real(self.dt) * ti.Vector(self.gravity, self.real)

    @ti.kernel
    def forces_fluid(self, s: ti.i32):
        """Symmetric pressure gradient and Monaghan's artificial viscosity between fluid particles."""
        for i in range(self.num_particles[None]):
            for n in range(self.num_neighbours[s, i]):
                k = self.neighbours[s, i, n]
                r = self.x[s, i] - self.x[s, k]
                distance = self.distance(r)
                grad_W = self.dW(distance) * r / distance  # [D]
                v_ij = self.v[s, i] - self.v[s, k]
                mu = self.real(self.h) * ti.min(v_ij.dot(r), 0.0) / (distance**2 + self.real(0.01 * self.h**2))
                viscous = self.real(-self.alpha * self.sound_speed) * mu / (0.5 * (self.rho[s, i] + self.rho[s, k]))
                pressure = self.p[s, i] / self.rho[s, i] ** 2 + self.p[s, k] / self.rho[s, k] ** 2
                self.v[s + 1, i] += self.real(-self.dt * self.mass) * (pressure + viscous) * grad_W

    @ti.kernel
    def forces_wall(self, s: ti.i32):
        """Pressure between a fluid particle and the wall particles, with their extrapolated pressure."""
        for i in range(self.num_particles[None]):
            for n in range(self.num_wall_neighbours[s, i]):
                w = self.wall_neighbours[s, i, n]
                r = self.x[s, i] - self.wall[w]
                distance = self.distance(r)
                grad_W = self.dW(distance) * r / distance
                pressure = self.p[s, i] / self.rho[s, i] ** 2 + self.wall_p[s, w] / self.wall_rho[s, w] ** 2
                self.v[s + 1, i] += self.real(-self.dt * self.mass) * pressure * grad_W

    @ti.kernel
    def advect(self, s: ti.i32):
        for i in range(self.num_particles[None]):
            x_new = self.x[s, i] + self.real(self.dt) * self.v[s + 1, i]
            for d in ti.static(range(self.dim)):
                x_new[d] = ti.min(ti.max(x_new[d], self.real(self.lower[d])), self.real(self.upper[d]))
            self.x[s + 1, i] = x_new

    @ti.kernel
    def carry_over(self):
        """The last substep of a frame is the first of the next."""
        for i in range(self.num_particles[None]):
            self.x[0, i] = self.x[self.substeps, i]
            self.v[0, i] = self.v[self.substeps, i]

    def _substep_kernels(self) -> tuple:
        """The differentiated kernels of one substep, in forward order."""
        return (self.density_fluid, self.density_wall, self.pressure, self.wall_sums, self.wall_state,
                self.gravity_step, self.forces_fluid, self.forces_wall, self.advect)

    def _frame(self) -> None:
        self.clear_fields()
        for s in range(self.substeps):
            self.find_neighbours(s)  # held constant: the lists are not differentiated
            for kernel in self._substep_kernels():
                kernel(s)
        if self.overflow[None]:
            raise RuntimeError("SPH neighbour or cell slots overflowed: raise max_neighbours / cell_capacity")

    def _frame_backward(self) -> None:
        for s in reversed(range(self.substeps)):
            for kernel in reversed(self._substep_kernels()):
                kernel.grad(s)

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

    def velocities(self) -> np.ndarray:
        """Velocities ``[N, D]`` (m/s) at the end of the last frame simulated."""
        return self._state(0)[1]

    def pressures(self) -> np.ndarray:
        """Pressures ``[N]`` (Pa) of the last substep simulated (the equation of state of its density)."""
        return self.p.to_numpy()[self.substeps - 1, : self.num_particles[None]].astype(float)

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
            for field in (self.x, self.v, self.rho, self.p, self.wall_sum_p, self.wall_sum_W, self.wall_p,
                          self.wall_rho):
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
