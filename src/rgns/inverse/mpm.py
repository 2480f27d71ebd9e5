"""MLS-MPM water in torch autograd: the optimisation baseline through the ground-truth solver's family.

:class:`rgns.physics.mpm.MPMSolver` (Taichi) keeps no per-substep history and declares no
gradients, so it cannot be differentiated as it is. This is the same scheme for water, written
with torch tensors so that autograd differentiates it: APIC transfers with quadratic B-splines,
the grid laid as the Taichi solver lays it (nodes on the walls, three cells of margin),
``tau = K J (J - 1) I + mu J (C + C^T)``, separating free-slip walls at the box bounds (no
friction, no obstacles), particles that cross a wall put back on it. On a free-falling and a
wall-hitting block it follows the Taichi solver to float32 rounding over a few frames
(``tests/test_inverse.py``). Sand and capsule obstacles are not ported.

Memory: each frame is a ``torch.utils.checkpoint`` segment, so the backward pass stores one
frame's substeps at a time plus one state ``(x, v, C, J)`` per frame.

The interface is :class:`~rgns.inverse.optimise.DifferentiableSimulator`: ``simulate(position,
velocity, steps)`` with per-frame velocities; a solve starts from rest in strain and affine
velocity (``J = 1``, ``C = 0``), as the data generator does.
"""
from __future__ import annotations

import itertools
import math

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint


class TorchMPM:
    """MLS-MPM water, differentiable (see the module docstring).

    Args: as :class:`rgns.physics.mpm.MPMSolver` for water: ``dim``, ``n_grid``, ``bounds``,
    ``frame_dt``, ``substeps``, ``gravity``, ``density``, ``bulk_modulus``, ``viscosity``.
    """

    def __init__(self, dim: int = 2, n_grid: int = 64, bounds=((0.1, 0.9), (0.1, 0.9)), frame_dt: float = 0.0025,
                 substeps: int = 10, gravity=(0.0, -9.81), density: float = 1000.0, bulk_modulus: float = 4.0e5,
                 viscosity: float = 0.0, checkpoint_frames: bool = True):
        bounds = torch.as_tensor(bounds, dtype=torch.float64)
        if dim not in (2, 3) or tuple(bounds.shape) != (dim, 2) or len(gravity) != dim:
            raise ValueError(f"bounds {tuple(bounds.shape)} and gravity {len(gravity)} must match dim={dim}")
        extent = bounds[:, 1] - bounds[:, 0]
        self.dim, self.frame_dt, self.substeps = dim, frame_dt, substeps
        self.dt = frame_dt / substeps
        self.dx = float(extent[0] / max(round(float(extent[0]) * n_grid), 1))
        self.lower, self.upper = bounds[:, 0].float(), bounds[:, 1].float()
        self.origin = (bounds[:, 0] - 3 * self.dx).float()
        self.grid_shape = tuple(int(math.ceil(float(e) / self.dx - 1e-6)) + 7 for e in extent)
        self.gravity = torch.as_tensor(gravity, dtype=torch.float32)
        self.p_vol = (0.5 * self.dx) ** dim
        self.p_mass = density * self.p_vol
        self.bulk_modulus, self.viscosity = bulk_modulus, viscosity
        self.checkpoint_frames = checkpoint_frames
        strides = [1] * dim
        for d in reversed(range(dim - 1)):
            strides[d] = strides[d + 1] * self.grid_shape[d + 1]
        self.strides = torch.tensor(strides)
        self.offsets = torch.tensor(list(itertools.product(range(3), repeat=dim)))  # [3^D, D]
        # grid nodes on or beyond a wall (within a thousandth of a cell): their velocity into it is removed
        index = torch.stack(torch.meshgrid(*[torch.arange(n) for n in self.grid_shape], indexing="ij"), -1)
        node = self.origin + index.reshape(-1, dim).float() * self.dx  # [G, D]
        tolerance = 1e-3 * self.dx
        self.at_lower = node < self.lower + tolerance  # [G, D]
        self.at_upper = node > self.upper - tolerance

    @classmethod
    def for_dataset(cls, metadata: dict, **options) -> "TorchMPM":
        """The solver of a dataset made by :mod:`rgns.data.generate` (its scene's grid, substeps and
        bulk modulus when the metadata has them)."""
        params = (metadata.get("generator") or {}).get("params") or {}
        solver = params.get("solver") or {}
        dim = int(metadata["dim"])
        settings = dict(dim=dim, bounds=metadata["bounds"], frame_dt=float(metadata["dt"]),
                        gravity=metadata.get("gravity") or params.get("gravity") or ([0.0, -9.81] + [0.0] * (dim - 2)))
        settings.update({k: solver[k] for k in ("n_grid", "substeps", "bulk_modulus", "viscosity", "density")
                         if k in solver})
        settings.update(options)
        return cls(**settings)

    # ------------------------------------------------------------------ one substep
    def substep(self, x: Tensor, v: Tensor, C: Tensor, J: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``x, v [N, D]``, ``C [N, D, D]``, ``J [N]`` -> the same after ``dt``."""
        dim, dx, inv_dx, dt = self.dim, self.dx, 1.0 / self.dx, self.dt
        identity = torch.eye(dim, dtype=x.dtype)
        Xp = (x - self.origin) * inv_dx
        base = torch.floor(Xp.detach() - 0.5).long()  # [N, D], the stencil's corner (not differentiated)
        fx = Xp - base
        w = torch.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])  # [3, N, D]
        tau = (self.bulk_modulus * J * (J - 1.0))[:, None, None] * identity
        if self.viscosity:
            tau = tau + self.viscosity * J[:, None, None] * (C + C.transpose(1, 2))
        affine = -dt * self.p_vol * 4 * inv_dx * inv_dx * tau + self.p_mass * C  # [N, D, D]
        cells = math.prod(self.grid_shape)
        # particles to grid
        weights, nodes, dposes = [], [], []
        grid_momentum = torch.zeros(cells, dim, dtype=x.dtype)
        grid_mass = torch.zeros(cells, dtype=x.dtype)
        for offset in self.offsets:
            dpos = (offset - fx) * dx  # [N, D]
            weight = _weight(w, offset)  # [N]
            node = ((base + offset) * self.strides).sum(-1)  # [N]
            momentum = weight[:, None] * (self.p_mass * v + (affine @ dpos.unsqueeze(-1)).squeeze(-1))
            grid_momentum = grid_momentum.index_add(0, node, momentum)
            grid_mass = grid_mass.index_add(0, node, weight * self.p_mass)
            weights.append(weight)
            nodes.append(node)
            dposes.append(dpos)
        # grid update: momentum to velocity, gravity, free-slip walls
        filled = grid_mass > 0
        grid_v = torch.where(filled[:, None], grid_momentum / torch.where(filled, grid_mass, 1.0)[:, None], 0.0)
        grid_v = torch.where(filled[:, None], grid_v + dt * self.gravity, grid_v)
        grid_v = torch.where(self.at_lower, grid_v.clamp(min=0.0), grid_v)  # no velocity into a lower wall
        grid_v = torch.where(self.at_upper, grid_v.clamp(max=0.0), grid_v)
        # grid to particles
        new_v = torch.zeros_like(v)
        new_C = torch.zeros_like(C)
        for weight, node, dpos in zip(weights, nodes, dposes):
            g_v = grid_v.index_select(0, node)  # [N, D]; its backward is an index_add
            new_v = new_v + weight[:, None] * g_v
            new_C = new_C + 4 * inv_dx * inv_dx * weight[:, None, None] * g_v.unsqueeze(-1) * dpos.unsqueeze(-2)
        x = x + dt * new_v
        J = J * (1.0 + dt * torch.diagonal(new_C, dim1=-2, dim2=-1).sum(-1))
        # a particle that crossed a wall goes back on it, its velocity into the wall removed
        below, above = x < self.lower, x > self.upper
        new_v = torch.where(below, new_v.clamp(min=0.0), torch.where(above, new_v.clamp(max=0.0), new_v))
        x = torch.maximum(torch.minimum(x, self.upper), self.lower)
        return x, new_v, new_C, J

    def frame(self, x: Tensor, v: Tensor, C: Tensor, J: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        for _ in range(self.substeps):
            x, v, C, J = self.substep(x, v, C, J)
        return x, v, C, J

    # ------------------------------------------------------------------ the simulator interface
    def _run(self, position: Tensor, velocity: Tensor, steps: int, keep: bool = False):
        # a start outside the box (an optimiser's iterate can drift there) goes onto its walls, as every
        # substep puts back a particle that crossed one: the grid covers the box and three cells more
        x = torch.maximum(torch.minimum(position, self.upper), self.lower)
        v = velocity / self.frame_dt  # per frame -> m/s
        C = torch.zeros(len(x), self.dim, self.dim, dtype=x.dtype)
        J = torch.ones(len(x), dtype=x.dtype)
        frames = [x.detach()]
        for _ in range(steps):
            if self.checkpoint_frames and torch.is_grad_enabled():
                x, v, C, J = checkpoint(self.frame, x, v, C, J, use_reentrant=False)
            else:
                x, v, C, J = self.frame(x, v, C, J)
            if keep:
                frames.append(x.detach())
        return x, v * self.frame_dt, frames

    def simulate(self, position: Tensor, velocity: Tensor, steps: int) -> tuple[Tensor, Tensor]:
        x, v, _ = self._run(position, velocity, steps)
        return x, v

    @torch.no_grad()
    def trajectory(self, position: Tensor, velocity: Tensor, steps: int) -> Tensor:
        return torch.stack(self._run(position, velocity, steps, keep=True)[2])


def _weight(w: Tensor, offset: Tensor) -> Tensor:
    """Product over the axes of the B-spline weights of one stencil offset: ``w [3, N, D] -> [N]``."""
    weight = w[offset[0], :, 0]
    for d in range(1, w.shape[-1]):
        weight = weight * w[offset[d], :, d]
    return weight
