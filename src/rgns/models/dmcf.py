"""DMCF: Deep Momentum-Conserving Fluids (Prantl, Ummenhofer, Koltun and Thuerey, NeurIPS 2022).

Explicit advection under gravity, then a position correction from continuous convolutions
(Ummenhofer et al. 2020) that ends in an antisymmetric convolution, so that the corrections of
every interacting pair cancel: the summed correction over the fluid and the boundary particles is
zero and linear momentum is conserved exactly (the walls take the reaction). Plain torch (Open3D's
operators are tied to old torch releases); the layers are in :mod:`rgns.nn.cconv`.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Mapping

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor, nn
from torch.nn import functional as F

from rgns.data.contract import KINEMATIC
from rgns.data.graph import batched_radius_graph
from rgns.models.base import Simulator, check_size
from rgns.nn.cconv import AntisymmetricConv, ContinuousConv, Neighbourhood, neighbourhood


def wall_samples(bounds: Tensor, spacing: float) -> tuple[Tensor, Tensor]:
    """Boundary particles on the faces of the box ``bounds [D, 2]``, at the centres of a grid of
    about ``spacing`` on each face (so no two faces share a corner sample), with inward normals.

    Shapes:
        bounds: ``[D, 2]``  ->  positions ``[M, D]``, normals ``[M, D]``
    """
    dim = bounds.size(0)
    positions, normals = [], []
    for axis, side in itertools.product(range(dim), (0, 1)):
        others = [d for d in range(dim) if d != axis]
        lines = []
        for d in others:
            lower, upper = bounds[d].tolist()
            count = max(math.ceil((upper - lower) / spacing), 1)
            lines.append(lower + (torch.arange(count, dtype=torch.float64) + 0.5) * (upper - lower) / count)
        face = torch.cartesian_prod(*lines).reshape(-1, dim - 1)  # [F, D - 1]
        points = torch.empty(len(face), dim, dtype=torch.float64)
        points[:, others] = face
        points[:, axis] = float(bounds[axis, side])
        normal = torch.zeros(len(face), dim, dtype=torch.float64)
        normal[:, axis] = 1.0 if side == 0 else -1.0  # into the box
        positions.append(points)
        normals.append(normal)
    return torch.cat(positions).float(), torch.cat(normals).float()


def particle_spacing(metadata: Mapping) -> float | None:
    """The dataset's particle spacing at rest, ``generator.params.spacing``, if it was generated here."""
    params = (metadata.get("generator") or {}).get("params") or {}
    # the model built by Hydra (SimulatorModule) sees its arguments instantiated recursively: there
    # ``params`` is the scene object that it describes, not its config
    spacing = params.get("spacing") if isinstance(params, Mapping) else getattr(params, "spacing", None)
    return None if spacing is None else float(spacing)


class DMCF(Simulator):
    r"""DMCF on the rgns state: advection, then a correction predicted from one frame.

    - advect: :math:`\mathbf v^* = \mathbf v^t + \mathbf g`, :math:`\mathbf x^* = \mathbf x^t + \mathbf v^*`
      (dt = 1, ``g`` per frame squared);
    - boundary particles: samples of the box's walls (``wall_spacing`` apart, inward normals)
      within the convolution radius of some particle at ``x^*``; they are conditions, and so are
      the dataset's kinematic particles;
    - encode: at every particle (fluid and boundary) the concatenation of a continuous
      convolution of the fluid features ``[1, v^* / std]`` over the fluid neighbours, one of the
      boundary features ``[1, normal]`` over the boundary neighbours, and a dense layer of the
      particle's own features (fluid or boundary), ``latent / 4`` wide each (DMCF: 8 of 32);
    - process: ``layers`` continuous convolutions ``latent`` wide, each
      ``h + CConv(relu h) + Dense(relu h)`` (the residual where the widths agree);
    - decode: the antisymmetric convolution of ``relu h`` to ``D`` outputs, times the dataset's
      acceleration std: the correction :math:`\Delta \mathbf x`, summing to zero over all particles;
    - ``next_velocity`` returns :math:`\mathbf x^* + \Delta \mathbf x - \mathbf x^t = \mathbf v^* + \Delta \mathbf x`.

    Every layer uses the same neighbourhoods: all pairs of particles at ``x^*`` (the state's and
    the boundary's) closer than ``radius_factor`` times the dataset's connectivity radius, found
    here (scipy), not the GNS graph the base class passes in. DMCF's multi-scale hierarchy
    (voxel-subsampled coarser levels) is not built: one scale, the finest.

    Args:
        metadata, history, noise_std, hard_walls: see :class:`~rgns.models.base.Simulator`
            (DMCF reads one frame: only ``v^t`` of the history).
        latent (int, optional): width of the hidden convolutions. (default: :obj:`96`)
        layers (int, optional): hidden convolutions between the input layer and the
            antisymmetric one. (default: :obj:`4`)
        kernel_size (int, optional): grid nodes per axis of every kernel (8: DMCF's 8 x 8).
            (default: :obj:`8`)
        radius_factor (float, optional): the convolution radius over the dataset's connectivity
            radius. (default: :obj:`4/3`, DMCF's WaterRamps 0.02 over its 0.015)
        wall_spacing (float, optional): spacing of the wall samples; ``None``: the dataset's
            particle spacing (``generator.params.spacing``) or, without one, half the
            connectivity radius. (default: :obj:`None`)
        gravity (list, optional): m/s^2, used when the metadata carries none; ``None``: -9.81
            along the second axis. Times ``metadata["dt"]`` squared: per frame squared.
            (default: :obj:`None`)
        embedding (int, optional): width of a particle-type embedding appended to the fluid
            features (multi-material data); 0: none, DMCF's inputs. (default: :obj:`0`)
        advect (bool, optional): read the scene at the advected positions ``x*`` (DMCF's);
            ``False`` (ablation): at ``x^t``, with the same inputs ``v*``. (default: :obj:`True`)
        antisymmetric (bool, optional): end in the antisymmetric convolution (DMCF's, momentum
            conserved); ``False`` (ablation): an ordinary continuous convolution, whose corrections
            need not sum to zero. (default: :obj:`True`)
    """

    display_name = "DMCF"

    def __init__(self, metadata: dict, history: int = 5, noise_std: float = 6.7e-4, latent: int = 96,
                 layers: int = 4, kernel_size: int = 8, radius_factor: float = 4 / 3,
                 wall_spacing: float | None = None, gravity: list | None = None, embedding: int = 0,
                 hard_walls: bool = False, advect: bool = True, antisymmetric: bool = True):
        super().__init__(metadata, history, noise_std, embedding, hard_walls)
        check_size("model.latent", latent)
        check_size("model.layers", layers)
        if not embedding:
            self.type_embedding = None  # DMCF's fluid features carry no type
        dim = self.dim
        self.conv_radius = radius_factor * self.radius
        self.kernel_size = kernel_size
        if metadata.get("gravity") is not None:
            gravity = metadata["gravity"]
        elif gravity is None:
            gravity = [0.0, -9.81] + [0.0] * (dim - 2)
        self.register_buffer("gravity", torch.as_tensor(gravity, dtype=torch.float32) * float(metadata["dt"]) ** 2)
        if wall_spacing is None:
            wall_spacing = particle_spacing(metadata) or self.radius / 2
        self.wall_spacing = wall_spacing
        walls, normals = wall_samples(self.bounds, wall_spacing)
        self.register_buffer("wall_position", walls, persistent=False)  # [M, D]
        self.register_buffer("wall_normal", normals, persistent=False)  # [M, D]

        width = max(latent // 4, 1)
        fluid_in, boundary_in = 1 + dim + embedding, 1 + dim
        self.fluid_conv = ContinuousConv(fluid_in, width, dim, kernel_size, dense=False)
        self.boundary_conv = ContinuousConv(boundary_in, width, dim, kernel_size, dense=False)
        self.fluid_dense = nn.Linear(fluid_in, width)
        self.boundary_dense = nn.Linear(boundary_in, width)
        widths = [3 * width] + [latent] * layers
        self.processor = nn.ModuleList(ContinuousConv(a, b, dim, kernel_size) for a, b in zip(widths, widths[1:]))
        self.advect, self.antisymmetric = bool(advect), bool(antisymmetric)
        if self.antisymmetric:
            self.decoder = AntisymmetricConv(widths[-1], dim, dim, kernel_size)
        else:
            self.decoder = ContinuousConv(widths[-1], dim, dim, kernel_size)

    # ---- the scene: particles at x* and the walls near them ------------------------------------

    def boundary_particles(self, position: Tensor, batch: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """The wall samples within the convolution radius of some particle of their graph.

        Shapes:
            position: ``[N, D]``, batch: ``[N]`` or None  ->  positions ``[M, D]``, normals ``[M, D]``, batch ``[M]``
        """
        walls = self.wall_position.detach().cpu().numpy().astype(np.float64)
        points = position.detach().cpu().numpy().astype(np.float64)
        graphs = np.zeros(len(points), dtype=np.int64) if batch is None else batch.cpu().numpy()
        kept, kept_batch = [], []
        for g in np.unique(graphs):
            distance, _ = cKDTree(points[graphs == g]).query(walls, distance_upper_bound=self.conv_radius)
            near = np.flatnonzero(distance < self.conv_radius)
            kept.append(near)
            kept_batch.append(np.full(len(near), g))
        index = torch.from_numpy(np.concatenate(kept)).to(position.device)
        wall_batch = torch.from_numpy(np.concatenate(kept_batch)).to(position.device)
        return self.wall_position[index].to(position.dtype), self.wall_normal[index].to(position.dtype), wall_batch

    def neighbourhood(self, position: Tensor, batch: Tensor) -> Neighbourhood:
        """All pairs closer than the convolution radius within each graph (both directions, no
        self-pairs), with their kernel lookups.  ``position [N, D]``, ``batch [N]`` (any order)"""
        order = torch.argsort(batch, stable=True)  # batched_radius_graph wants the graphs contiguous
        edge_index = order[batched_radius_graph(position[order], self.conv_radius, batch[order])]  # [2, E]
        return neighbourhood(position, edge_index, self.conv_radius, self.kernel_size)

    # ---- the network ----------------------------------------------------------------------------

    def encode(self, fluid: Tensor, boundary: Tensor, is_fluid: Tensor, neighbourhood: Neighbourhood) -> Tensor:
        """DMCF's input layer at every particle: ``[CConv over fluid senders, CConv over boundary
        senders, Dense of its own features]``.

        Shapes:
            fluid: ``[N, 1 + D (+ embedding)]``, boundary: ``[N, 1 + D]`` (each read only on its
            own particles), is_fluid: ``[N]``  ->  ``[N, 3 latent / 4]``
        """
        from_fluid = neighbourhood.subset(is_fluid[neighbourhood.sender])
        from_boundary = neighbourhood.subset(~is_fluid[neighbourhood.sender])
        own = torch.where(is_fluid.unsqueeze(-1), self.fluid_dense(fluid), self.boundary_dense(boundary))
        return torch.cat([self.fluid_conv(fluid, from_fluid), self.boundary_conv(boundary, from_boundary), own], dim=-1)

    def process(self, h: Tensor, neighbourhood: Neighbourhood) -> Tensor:
        for conv in self.processor:
            update = conv(F.relu(h), neighbourhood)
            h = h + update if update.shape == h.shape else update
        return h

    def decode(self, h: Tensor, neighbourhood: Neighbourhood) -> Tensor:
        """The correction Δx ``[N, D]`` in position units: its sum over the particles is zero
        (with ``antisymmetric``)."""
        return self.decoder(F.relu(h), neighbourhood) * self.acc_std_noisy  # one scale per axis keeps the sum zero

    def correction(self, advected: Tensor, velocity: Tensor, particle_type: Tensor,
                   batch: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Δx at the state's particles and at the wall samples near them.

        Shapes:
            advected: ``[N, D]`` (x*), velocity: ``[N, D]`` (v*), particle_type: ``[N]``
            ->  ``[N, D]``, ``[M, D]``
        """
        n = advected.size(0)
        batch = torch.zeros(n, dtype=torch.long, device=advected.device) if batch is None else batch
        wall, normal, wall_batch = self.boundary_particles(advected, batch)
        position = torch.cat([advected, wall])  # [N + M, D]
        is_fluid = torch.cat([particle_type != KINEMATIC, torch.zeros(len(wall), dtype=torch.bool, device=wall.device)])
        ones = position.new_ones(len(position), 1)
        speed = torch.cat([velocity / self.vel_std_noisy, torch.zeros_like(wall)])  # v* of the fluid, O(1)
        fluid = [ones, speed]
        if self.type_embedding is not None:  # read only at the fluid particles
            fluid.append(F.pad(self.type_embedding(particle_type), (0, 0, 0, len(wall))))
        fluid = torch.cat(fluid, dim=-1)
        # boundary features: the wall's inward normal; the dataset's kinematic particles carry none
        boundary = torch.cat([ones, torch.cat([torch.zeros_like(advected), normal])], dim=-1)
        neighbours = self.neighbourhood(position, torch.cat([batch, wall_batch]))
        h = self.encode(fluid, boundary, is_fluid, neighbours)
        h = self.process(h, neighbours)
        correction = self.decode(h, neighbours)  # [N + M, D]
        return correction[:n], correction[n:]

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        velocity = velocity_history[:, -1] + self.gravity  # v*, dt = 1
        advected = position + velocity  # x*
        correction, _ = self.correction(advected if self.advect else position, velocity, particle_type, batch)
        return velocity + correction  # (x* + Δx) - x^t

    def extra_repr(self) -> str:
        return (f"{super().extra_repr()}, conv_radius={self.conv_radius:g}, kernel_size={self.kernel_size}, "
                f"walls={len(self.wall_position)} at {self.wall_spacing:g}")
