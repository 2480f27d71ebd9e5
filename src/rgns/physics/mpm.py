"""MLS-MPM (Hu et al. 2018) in 2D and 3D: weakly compressible water and Drucker-Prager sand.

The grid is laid so that its nodes fall on the walls of the box ``bounds`` (spacing close to
``1 / n_grid``, chosen so that the first dimension's extent is whole cells) and reaches three cells
beyond them. Walls at the box bounds and static capsule obstacles (ramps) are boundary
conditions on the grid velocity (separating contact with Coulomb friction), and a particle that
an interpolation error carries across one is projected back onto its surface, so no particle
ever leaves the box or enters an obstacle.

Constitutive models, as Kirchhoff stress ``tau``:

- water (type 5): ``tau = K J (J - 1) I + mu J (C + C^T)``, J the volume ratio, K the bulk
  modulus (sound speed ``sqrt(K / rho)``), C the APIC affine velocity (~ grad v), mu viscosity;
- sand (type 6): St. Venant-Kirchhoff in Hencky strain with Drucker-Prager return mapping
  (Klar et al. 2016), no cohesion.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import taichi as ti

from rgns.physics.materials import SAND, WATER
from rgns.physics.geometry import Capsule
from rgns.physics.runtime import ensure_taichi


@ti.data_oriented
class MPMSolver:
    """MLS-MPM with APIC transfers and quadratic B-splines.

    Args:
        dim: 2 or 3.
        capacity: the most particles one rollout may have (fields are allocated once).
        n_grid: grid cells per unit length (the spacing is adjusted so the box spans whole cells).
        bounds: ``[[lo, hi]] * dim``, the walls.
        frame_dt: seconds between two output frames.
        substeps: solver steps per frame (CFL: ``(c + |v|) * frame_dt / substeps < ~0.4 / n_grid``).
        gravity: ``[dim]`` in m/s^2.
        density: water's rest density (kg/m^3).
        bulk_modulus: water's K (Pa); sound speed ``sqrt(K / density)``.
        viscosity: water's dynamic viscosity (Pa s).
        sand_density, youngs_modulus, poisson_ratio, friction_angle: sand (kg/m^3, Pa, -, degrees).
        wall_friction: Coulomb coefficient at walls and obstacles (0: free slip).
        max_obstacles: how many capsules :meth:`rollout` accepts.
    """

    def __init__(
        self,
        dim: int = 2,
        capacity: int = 4096,
        n_grid: int = 64,
        bounds: Sequence[Sequence[float]] = ((0.1, 0.9), (0.1, 0.9)),
        frame_dt: float = 0.0025,
        substeps: int = 10,
        gravity: Sequence[float] = (0.0, -9.81),
        density: float = 1000.0,
        bulk_modulus: float = 4.0e5,
        viscosity: float = 0.0,
        sand_density: float = 2200.0,
        youngs_modulus: float = 3.5e5,
        poisson_ratio: float = 0.3,
        friction_angle: float = 40.0,
        wall_friction: float = 0.0,
        max_obstacles: int = 8,
    ):
        ensure_taichi()
        bounds = np.asarray(bounds, dtype=float)
        if dim not in (2, 3) or bounds.shape != (dim, 2) or len(gravity) != dim:
            raise ValueError(f"bounds {bounds.shape} and gravity {len(gravity)} must match dim={dim}")
        extent = bounds[:, 1] - bounds[:, 0]
        self.dim, self.capacity, self.n_grid = dim, capacity, n_grid
        self.dx = float(extent[0] / max(round(extent[0] * n_grid), 1))
        # nodes at lower + k dx: walls on nodes; 3 cells of margin for the B-spline stencil
        self.origin = tuple((bounds[:, 0] - 3 * self.dx).tolist())
        self.grid_shape = tuple(int(math.ceil(e / self.dx - 1e-6)) + 7 for e in extent)
        self.frame_dt, self.substeps = frame_dt, substeps
        self.dt = frame_dt / substeps
        self.lower, self.upper = tuple(bounds[:, 0].tolist()), tuple(bounds[:, 1].tolist())
        self.gravity = tuple(float(g) for g in gravity)
        self.p_vol = (0.5 * self.dx) ** dim  # cancels out of the accelerations; kept physical
        self.density, self.bulk_modulus, self.viscosity = density, bulk_modulus, viscosity
        self.sand_density = sand_density
        self.mu = youngs_modulus / (2 * (1 + poisson_ratio))  # Lame parameters of sand
        self.lam = youngs_modulus * poisson_ratio / ((1 + poisson_ratio) * (1 - 2 * poisson_ratio))
        sin_phi = math.sin(math.radians(friction_angle))
        self.alpha = math.sqrt(2 / 3) * 2 * sin_phi / (3 - sin_phi)  # Drucker-Prager cone
        self.max_obstacles = max_obstacles

        vec, mat = ti.types.vector(dim, ti.f32), ti.types.matrix(dim, dim, ti.f32)
        self.x = ti.field(vec, capacity)  # position
        self.v = ti.field(vec, capacity)  # velocity
        self.C = ti.field(mat, capacity)  # APIC affine velocity
        self.F = ti.field(mat, capacity)  # elastic deformation gradient (sand)
        self.J = ti.field(ti.f32, capacity)  # volume ratio (water)
        self.material = ti.field(ti.i32, capacity)
        self.num_particles = ti.field(ti.i32, ())
        self.grid_v = ti.field(vec, self.grid_shape)  # momentum, then velocity
        self.grid_m = ti.field(ti.f32, self.grid_shape)
        self.obstacle_start = ti.field(vec, max_obstacles)
        self.obstacle_end = ti.field(vec, max_obstacles)
        self.obstacle_radius = ti.field(ti.f32, max_obstacles)
        self.num_obstacles = ti.field(ti.i32, ())
        self.friction = ti.field(ti.f32, ())
        self.wall_friction = wall_friction

    @property
    def wall_friction(self) -> float:
        """Coulomb coefficient at walls and obstacles; may change between rollouts."""
        return float(self.friction[None])

    @wall_friction.setter
    def wall_friction(self, value: float) -> None:
        self.friction[None] = value

    # ------------------------------------------------------------------ boundaries
    @ti.func
    def contact(self, v, normal):
        """Separating contact with Coulomb friction: remove the velocity into the surface."""
        vn = v.dot(normal)
        if vn < 0:
            tangential = v - vn * normal
            speed = tangential.norm()
            scale = 0.0
            if speed > 1e-12:
                scale = ti.max(0.0, 1.0 - self.friction[None] * (-vn) / speed)
            v = tangential * scale
        return v

    @ti.func
    def obstacle_distance(self, k, p):
        """Signed distance of point p to capsule k and the outward normal there."""
        a, b = self.obstacle_start[k], self.obstacle_end[k]
        ab = b - a
        t = ti.math.clamp((p - a).dot(ab) / ti.max(ab.dot(ab), 1e-12), 0.0, 1.0)
        d = p - (a + t * ab)
        length = d.norm()
        normal = d / ti.max(length, 1e-9)
        return length - self.obstacle_radius[k], normal

    @ti.func
    def grid_boundary(self, pos, v):
        tolerance = 1e-3 * self.dx  # nodes on a wall hold it
        for d in ti.static(range(self.dim)):
            normal = ti.Vector.unit(self.dim, d, ti.f32)
            if pos[d] < self.lower[d] + tolerance:
                v = self.contact(v, normal)
            if pos[d] > self.upper[d] - tolerance:
                v = self.contact(v, -normal)
        for k in range(self.num_obstacles[None]):
            phi, normal = self.obstacle_distance(k, pos)
            if phi < 0.5 * self.dx:  # nodes within half a cell of the surface hold the contact
                v = self.contact(v, normal)
        return v

    @ti.func
    def project_particle(self, p):
        """Put a particle that crossed a wall or entered an obstacle back on the surface."""
        x, v = self.x[p], self.v[p]
        for d in ti.static(range(self.dim)):
            if x[d] < self.lower[d]:
                x[d] = self.lower[d]
                v[d] = ti.max(v[d], 0.0)
            if x[d] > self.upper[d]:
                x[d] = self.upper[d]
                v[d] = ti.min(v[d], 0.0)
        for k in range(self.num_obstacles[None]):
            phi, normal = self.obstacle_distance(k, x)
            if phi < 0:
                x -= phi * normal
                v -= ti.min(v.dot(normal), 0.0) * normal
        self.x[p], self.v[p] = x, v

    # ------------------------------------------------------------------ materials
    @ti.func
    def kirchhoff_stress(self, p):
        dim = ti.static(self.dim)
        identity = ti.Matrix.identity(ti.f32, dim)
        tau = ti.Matrix.zero(ti.f32, dim, dim)
        if self.material[p] == WATER:
            J = self.J[p]
            tau = self.bulk_modulus * J * (J - 1.0) * identity
            tau += self.viscosity * J * (self.C[p] + self.C[p].transpose())
        else:  # sand: Hencky strain, tau = U (2 mu log S + lam tr(log S)) U^T
            U, sig, V = ti.svd(self.F[p])
            log_sig = ti.Matrix.zero(ti.f32, dim, dim)
            for d in ti.static(range(dim)):
                log_sig[d, d] = ti.log(ti.max(ti.abs(sig[d, d]), 1e-6))
            trace = log_sig.trace()
            tau = U @ (2.0 * self.mu * log_sig + self.lam * trace * identity) @ U.transpose()
        return tau

    @ti.func
    def drucker_prager(self, F):
        """Return-map the elastic deformation gradient onto the Drucker-Prager cone."""
        dim = ti.static(self.dim)
        U, sig, V = ti.svd(F)
        eps = ti.Vector.zero(ti.f32, dim)
        for d in ti.static(range(dim)):
            eps[d] = ti.log(ti.max(ti.abs(sig[d, d]), 1e-6))
        trace = eps.sum()
        eps_hat = eps - trace / dim
        eps_hat_norm = eps_hat.norm() + 1e-12
        dq = eps_hat_norm + (dim * self.lam + 2 * self.mu) / (2 * self.mu) * trace * self.alpha
        if trace >= 0:  # expansion: cohesionless sand carries no tension
            eps = ti.Vector.zero(ti.f32, dim)
        elif dq > 0:  # outside the cone: project onto it
            eps = eps - dq / eps_hat_norm * eps_hat
        new_sig = ti.Matrix.zero(ti.f32, dim, dim)
        for d in ti.static(range(dim)):
            new_sig[d, d] = ti.exp(eps[d])
        return U @ new_sig @ V.transpose()

    # ------------------------------------------------------------------ one step
    @ti.kernel
    def substep(self):
        dim = ti.static(self.dim)
        dx, inv_dx, dt = self.dx, 1.0 / self.dx, self.dt
        origin = ti.Vector(self.origin, ti.f32)
        for I in ti.grouped(self.grid_m):
            self.grid_v[I] = ti.Vector.zero(ti.f32, dim)
            self.grid_m[I] = 0.0
        # particles to grid
        for p in range(self.num_particles[None]):
            Xp = (self.x[p] - origin) * inv_dx
            base = ti.cast(Xp - 0.5, ti.i32)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            rho = self.density if self.material[p] == WATER else self.sand_density
            p_mass = rho * self.p_vol
            affine = -dt * self.p_vol * 4 * inv_dx * inv_dx * self.kirchhoff_stress(p) + p_mass * self.C[p]
            for offset in ti.static(ti.grouped(ti.ndrange(*((3,) * dim)))):
                dpos = (offset - fx) * dx
                weight = 1.0
                for d in ti.static(range(dim)):
                    weight *= w[offset[d]][d]
                self.grid_v[base + offset] += weight * (p_mass * self.v[p] + affine @ dpos)
                self.grid_m[base + offset] += weight * p_mass
        # grid update: momentum to velocity, gravity, walls and obstacles
        for I in ti.grouped(self.grid_m):
            if self.grid_m[I] > 0:
                v = self.grid_v[I] / self.grid_m[I]
                for d in ti.static(range(dim)):
                    v[d] += dt * self.gravity[d]
                self.grid_v[I] = self.grid_boundary(origin + I * dx, v)
        # grid to particles
        for p in range(self.num_particles[None]):
            Xp = (self.x[p] - origin) * inv_dx
            base = ti.cast(Xp - 0.5, ti.i32)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = ti.Vector.zero(ti.f32, dim)
            new_C = ti.Matrix.zero(ti.f32, dim, dim)
            for offset in ti.static(ti.grouped(ti.ndrange(*((3,) * dim)))):
                dpos = (offset - fx) * dx
                weight = 1.0
                for d in ti.static(range(dim)):
                    weight *= w[offset[d]][d]
                g_v = self.grid_v[base + offset]
                new_v += weight * g_v
                new_C += 4 * inv_dx * inv_dx * weight * g_v.outer_product(dpos)
            self.v[p], self.C[p] = new_v, new_C
            self.x[p] += dt * new_v
            if self.material[p] == WATER:
                self.J[p] *= 1.0 + dt * new_C.trace()
            else:
                self.F[p] = self.drucker_prager((ti.Matrix.identity(ti.f32, dim) + dt * new_C) @ self.F[p])
            self.project_particle(p)

    # ------------------------------------------------------------------ python side
    def reset(self, position: np.ndarray, velocity: np.ndarray, material: np.ndarray,
              obstacles: Sequence[Capsule] = (), pressure: np.ndarray | None = None) -> None:
        """Load a state: ``position``, ``velocity`` ``[N, D]``, ``material`` ``[N]`` (5 water, 6 sand).

        ``pressure`` ``[N]`` (Pa, optional) pre-compresses water (``J = 1 - p / K``): a tank
        started with its hydrostatic pressure is at rest from the first step.
        """
        n = len(position)
        if n > self.capacity:
            raise ValueError(f"{n} particles exceed the solver's capacity {self.capacity}")
        if len(obstacles) > self.max_obstacles:
            raise ValueError(f"{len(obstacles)} obstacles exceed max_obstacles={self.max_obstacles}")
        if not np.isin(material, (WATER, SAND)).all():
            raise ValueError(f"materials must be {WATER} (water) or {SAND} (sand), got {np.unique(material)}")
        dim = self.dim

        def padded(values, shape, dtype):
            out = np.zeros((self.capacity, *shape), dtype)
            out[:n] = values
            return out

        self.x.from_numpy(padded(position, (dim,), np.float32))
        self.v.from_numpy(padded(velocity, (dim,), np.float32))
        self.C.from_numpy(np.zeros((self.capacity, dim, dim), np.float32))
        self.F.from_numpy(np.broadcast_to(np.eye(dim, dtype=np.float32), (self.capacity, dim, dim)).copy())
        volume_ratio = np.ones(self.capacity, np.float32)
        if pressure is not None:
            volume_ratio[:n] = 1.0 - np.asarray(pressure) / self.bulk_modulus
        self.J.from_numpy(volume_ratio)
        self.material.from_numpy(padded(material, (), np.int32))
        self.num_particles[None] = n
        starts = np.zeros((self.max_obstacles, dim), np.float32)
        ends = np.zeros((self.max_obstacles, dim), np.float32)
        radii = np.zeros(self.max_obstacles, np.float32)
        for k, capsule in enumerate(obstacles):
            starts[k], ends[k], radii[k] = capsule.start, capsule.end, capsule.radius
        self.obstacle_start.from_numpy(starts)
        self.obstacle_end.from_numpy(ends)
        self.obstacle_radius.from_numpy(radii)
        self.num_obstacles[None] = len(obstacles)

    def positions(self) -> np.ndarray:
        """Current positions ``[N, D]`` float32."""
        return self.x.to_numpy()[: self.num_particles[None]]

    def velocities(self) -> np.ndarray:
        return self.v.to_numpy()[: self.num_particles[None]]

    def advance(self, num_frames: int = 1) -> None:
        for _ in range(num_frames * self.substeps):
            self.substep()

    def rollout(self, position: np.ndarray, velocity: np.ndarray, material: np.ndarray,
                num_frames: int, obstacles: Sequence[Capsule] = (),
                pressure: np.ndarray | None = None) -> np.ndarray:
        """Simulate ``num_frames - 1`` frames from a state; returns positions ``[num_frames, N, D]``."""
        self.reset(position, velocity, material, obstacles, pressure)
        trajectory = np.empty((num_frames, len(position), self.dim), np.float32)
        trajectory[0] = position
        for frame in range(1, num_frames):
            self.advance(1)
            trajectory[frame] = self.positions()
        if not np.isfinite(trajectory).all():
            raise FloatingPointError("MPM rollout produced NaN or Inf; lower frame_dt / substeps ratio")
        return trajectory
