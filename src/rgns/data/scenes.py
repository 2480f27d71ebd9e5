"""Scenes: how initial states are drawn and handed to a solver.

A scene is built from its config (``conf/scene/*.yaml``, a ``_target_`` here) and makes one
trajectory at a time::

    scene = hydra.utils.instantiate(scene_cfg)
    position, particle_type = scene.trajectory(rng, num_frames)  # [T, N, D] float32, [N] int64

Positions are in metres in the box ``bounds``; frames are ``dt`` seconds apart. Static obstacles
(ramps) are exported as kinematic particles (type 3) after the moving ones, at the same place in
every frame. The solver is made on first use (``solver`` is a partial: Taichi starts only in the
process that simulates).
"""
from __future__ import annotations

import inspect
import math
from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from rgns.data.contract import KINEMATIC, WATER
from rgns.physics.geometry import Capsule, lattice  # noqa: F401 (lattice re-exported)


class Scene:
    """What every scene shares: the box, the frame rate, the particle spacing and the solver.

    Args:
        name: the scene's name (metadata).
        dim: 2 or 3.
        bounds: ``[[lo, hi]] * dim`` in metres: the walls.
        dt: seconds between frames.
        connectivity_radius: the graph radius the dataset is meant for (metadata).
        gravity: ``[dim]`` m/s^2.
        spacing: distance between neighbouring particles at rest (m).
        material: particle type of the moving particles (5 water, 6 sand).
        solver: a partial of a solver class (``rollout(position, velocity, material, num_frames,
            obstacles)``), completed here with dim, bounds, frame_dt, gravity and capacity, and
            spacing where the solver takes one (SPH).
        capacity: the most particles one trajectory may have.
        num_frames: frames per trajectory (``sequence_length + 1``).
        splits: trajectories per split, ``{train, valid, test}``.
    """

    def __init__(self, name: str, dim: int, bounds: Sequence[Sequence[float]], dt: float,
                 connectivity_radius: float, gravity: Sequence[float], spacing: float,
                 solver: Callable, capacity: int = 4096, material: int = WATER,
                 num_frames: int = 300, splits: dict | None = None):
        self.name, self.dim = name, dim
        self.bounds = np.asarray(bounds, dtype=float)  # [D, 2]
        self.lower, self.upper = self.bounds[:, 0], self.bounds[:, 1]
        self.dt, self.connectivity_radius = dt, connectivity_radius
        self.gravity = tuple(gravity)
        self.spacing, self.material, self.capacity = spacing, material, capacity
        self.num_frames, self.splits = num_frames, dict(splits or {})
        self._solver_factory, self._solver = solver, None

    @property
    def solver(self):
        if self._solver is None:
            scene = dict(dim=self.dim, bounds=self.bounds.tolist(), frame_dt=self.dt, gravity=self.gravity,
                         capacity=self.capacity)
            if "spacing" in inspect.signature(self._solver_factory).parameters:  # SPH: the mass and kernel size
                scene["spacing"] = self.spacing
            self._solver = self._solver_factory(**scene)
        return self._solver

    def sample(self, rng: np.random.Generator) -> dict:
        """An initial state: ``position``, ``velocity`` ``[N, D]`` and ``obstacles`` (capsules)."""
        raise NotImplementedError

    def trajectory(self, rng: np.random.Generator, num_frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Simulate one trajectory: positions ``[T, N, D]`` float32 and types ``[N]`` int64."""
        num_frames = num_frames or self.num_frames
        state = self.sample(rng)
        material = np.full(len(state["position"]), self.material, np.int64)
        position = self.solver.rollout(state["position"], state["velocity"], material, num_frames,
                                       obstacles=state["obstacles"])  # [T, N, D]
        static = [capsule.sample(self.spacing) for capsule in state["obstacles"]]
        if static:
            static = np.concatenate(static).astype(np.float32)  # [M, D]
            position = np.concatenate([position, np.broadcast_to(static, (num_frames, *static.shape))], axis=1)
            material = np.concatenate([material, np.full(len(static), KINEMATIC, np.int64)])
        return position.astype(np.float32), material


class BodiesScene(Scene):
    """Bodies of random shape (boxes and ellipses), size, position and velocity, optionally
    with random ramps: WaterDrop (no ramps), WaterRamps (1-4 ramps), Sand, Water-3D.

    Args:
        num_bodies: ``[min, max]`` bodies per trajectory.
        body_size: ``[min, max]`` extent of a body along each axis (m).
        shapes: drawn from ``box`` and ``ball`` (an ellipse / ellipsoid in the body's box).
        max_speed: each body's initial velocity is uniform in ``[-max_speed, max_speed]^D`` (m/s).
        particles: ``[min, max]`` moving particles per trajectory.
        num_ramps: ``[min, max]`` ramps (2D only); 0 for none.
        ramp_length: ``[min, max]`` (m); ramp_angle: ``[min, max]`` slope in degrees (either sign).
        ramp_radius: half thickness of a ramp (m).
    """

    def __init__(self, num_bodies: Sequence[int] = (1, 2), body_size: Sequence[float] = (0.06, 0.14),
                 shapes: Sequence[str] = ("box", "ball"), max_speed: float = 1.0,
                 particles: Sequence[int] = (100, 400), num_ramps: Sequence[int] = (0, 0),
                 ramp_length: Sequence[float] = (0.15, 0.35), ramp_angle: Sequence[float] = (10.0, 40.0),
                 ramp_radius: float = 0.0065, **common):
        super().__init__(**common)
        self.num_bodies, self.body_size, self.shapes = tuple(num_bodies), tuple(body_size), tuple(shapes)
        self.max_speed, self.particles = max_speed, tuple(particles)
        self.num_ramps, self.ramp_length, self.ramp_angle = tuple(num_ramps), tuple(ramp_length), tuple(ramp_angle)
        self.ramp_radius = ramp_radius
        if max(self.num_ramps) > 0 and self.dim != 2:
            raise ValueError("ramps are 2D only")

    def sample_ramps(self, rng: np.random.Generator) -> list[Capsule]:
        ramps = []
        margin = self.ramp_radius + 2 * self.spacing
        while len(ramps) < rng.integers(self.num_ramps[0], self.num_ramps[1] + 1):
            length = rng.uniform(*self.ramp_length)
            angle = math.radians(rng.uniform(*self.ramp_angle)) * rng.choice([-1.0, 1.0])
            half = 0.5 * length * np.array([math.cos(angle), math.sin(angle)])
            # ramps live in the lower 70% of the box, so bodies have room to start above them
            top = self.lower[1] + 0.7 * (self.upper[1] - self.lower[1])
            low, high = self.lower + np.abs(half) + margin, np.array([self.upper[0], top]) - np.abs(half) - margin
            centre = rng.uniform(low, high)
            ramps.append(Capsule(tuple((centre - half).tolist()), tuple((centre + half).tolist()), self.ramp_radius))
        return ramps

    def sample_body(self, rng: np.random.Generator) -> np.ndarray:
        size = rng.uniform(*self.body_size, size=self.dim)
        margin = 2 * self.spacing
        centre = rng.uniform(self.lower + size / 2 + margin, self.upper - size / 2 - margin)
        points = lattice(centre - size / 2, centre + size / 2, self.spacing)
        if rng.choice(self.shapes) == "ball":
            points = points[(((points - centre) / (size / 2)) ** 2).sum(-1) <= 1.0]
        return points

    def sample(self, rng: np.random.Generator) -> dict:
        for _ in range(1000):
            obstacles = self.sample_ramps(rng)
            bodies, velocities = [], []
            for _ in range(rng.integers(self.num_bodies[0], self.num_bodies[1] + 1)):
                body = self.sample_body(rng)
                clear = all(c.signed_distance(body).min() > 2 * self.spacing for c in obstacles)
                if bodies:
                    clear &= cKDTree(np.concatenate(bodies)).query(body)[0].min() > 3 * self.spacing
                if clear and len(body):
                    bodies.append(body)
                    velocities.append(np.broadcast_to(rng.uniform(-self.max_speed, self.max_speed, self.dim), body.shape))
            count = sum(len(b) for b in bodies)
            if bodies and self.particles[0] <= count <= self.particles[1]:
                return {"position": np.concatenate(bodies), "velocity": np.concatenate(velocities),
                        "obstacles": obstacles}
        raise RuntimeError(f"{self.name}: no layout with {self.particles} particles in 1000 draws; "
                           "widen `particles` or change `body_size`")


class DamBreakScene(Scene):
    """A water column of width ``width`` and height ``height_ratio * width`` against the left
    wall, at rest, released at t = 0 (Martin & Moyce 1952). No randomness: every trajectory is
    the same.
    """

    def __init__(self, width: float = 0.15, height_ratio: float = 2.0, **common):
        super().__init__(**common)
        self.width, self.height_ratio = width, height_ratio

    def sample(self, rng: np.random.Generator) -> dict:
        extent = np.full(self.dim, self.width)
        extent[1] = self.height_ratio * self.width
        # the column spans whole spacings, flush with the left wall and the floor
        counts = np.round(extent / self.spacing).astype(int)
        position = lattice(self.lower, self.lower + counts * self.spacing, self.spacing)
        if self.dim == 3:  # the column spans the whole depth of the tank
            depth = self.upper[2] - self.lower[2]
            cells = int(np.floor(depth / self.spacing + 1e-6))
            position = lattice(self.lower, np.array([self.lower[0] + counts[0] * self.spacing,
                                                     self.lower[1] + counts[1] * self.spacing,
                                                     self.lower[2] + cells * self.spacing]), self.spacing)
        return {"position": position, "velocity": np.zeros_like(position), "obstacles": []}
