"""EGNN: the E(n)-equivariant graph network of Satorras, Hoogeboom and Welling (2021) as a
particle simulator (as in LagrangeBench, Toshev et al. 2023).

A box under gravity is not symmetric under rotations, so the symmetry is broken only through
named vector inputs that rotate with the scene: gravity, a vector ``[D]``, and the walls, for
each wall the vector from the particle to its nearest point on it, clipped at the connectivity
radius R (``[N, W, D]``). Everything else the network sees is invariant, so rotating, reflecting
and translating the whole scene (positions, velocity history, gravity and walls) rotates,
reflects and translates the prediction (:meth:`EGNN.predict`; tests/test_egnn.py checks it).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from rgns.data.contract import KINEMATIC
from rgns.models.base import Simulator, check_size, dataset_gravity
from rgns.nn.egnn import EquivariantLayer, smooth_norm


class EGNN(Simulator):
    r"""E(n)-equivariant message passing that moves the particles through one frame.

    - encode: ``h^0 = Linear(invariants)``: the speeds ``|v|`` of the history and their
      components along gravity, each wall's distance ``|w|`` and component along gravity, and the
      type embedding; velocities over one scalar scale (an axis-wise mean or std would not rotate);
    - process: ``layers`` :class:`~rgns.nn.egnn.EquivariantLayer` s, read as substeps of the
      frame: layer l estimates the next velocity ``u^l`` from ``v^t``, the relative positions
      ``x_i - x_j`` of the neighbours, the walls ``x_i - x_w`` and gravity, and moves every
      particle by ``u^l / layers``;
    - decode: the position reached is the next position, so ``v^{t+1} = p^{t+1} - p^t``, the
      mean of the layers' estimates. Kinematic particles keep ``v^t`` through the layers.

    Positions are in units of R; the vector terms of the layers in units of the acceleration's
    scale (the RMS over axes of the noisy acceleration std), so the learned scalars are O(1).

    Args:
        metadata, history, noise_std, embedding, hard_walls: see :class:`~rgns.models.base.Simulator`;
            gravity is ``metadata["gravity"]`` (m/s^2) times ``dt^2``, or else ``acc_mean`` (as
            :class:`~rgns.evaluation.baselines.Ballistic`).
        latent (int, optional): width of h and the messages. (default: :obj:`264`)
        layers (int, optional): equivariant layers. (default: :obj:`5`)
        coordinate_aggregation, normalise, tanh, coordinate_gain: the stabilisers of
            :class:`~rgns.nn.egnn.EquivariantLayer`.
    """

    display_name = "EGNN"

    def __init__(self, metadata: dict, history: int = 5, noise_std: float = 6.7e-4, latent: int = 264,
                 layers: int = 5, embedding: int = 16, hard_walls: bool = False,
                 coordinate_aggregation: str = "mean", normalise: bool = False, tanh: bool = False,
                 coordinate_gain: float = 1e-3):
        super().__init__(metadata, history, noise_std, embedding, hard_walls)
        check_size("model.latent", latent)
        check_size("model.layers", layers)
        self.register_buffer("gravity", dataset_gravity(metadata))  # [D], position units per frame^2
        walls = 2 * self.dim
        invariants = 2 * history + 2 * walls + embedding
        self.encoder = nn.Linear(invariants, latent)
        self.processor = nn.ModuleList(
            EquivariantLayer(latent, coordinate_aggregation, normalise, tanh, coordinate_gain,
                             update_features=i < layers - 1)  # the last h would go unused
            for i in range(layers))

    # ---- the scalar scales: one per quantity, so that they commute with rotations --------------

    @property
    def velocity_scale(self) -> Tensor:
        return self.vel_std_noisy.pow(2).mean().sqrt()

    @property
    def acceleration_scale(self) -> Tensor:
        return self.acc_std_noisy.pow(2).mean().sqrt()

    def vector_inputs(self, position: Tensor) -> tuple[Tensor, Tensor]:
        """Gravity and the walls of the box ``bounds``: for each wall, the vector from the particle
        to its nearest point on the wall's plane, clipped to length R (lower walls, then upper).

        Shapes:
            position: ``[N, D]``  ->  gravity ``[D]``, walls ``[N, 2 D, D]``
        """
        lower = torch.diag_embed((self.bounds[:, 0] - position).clamp(-self.radius, self.radius))  # [N, D, D]
        upper = torch.diag_embed((self.bounds[:, 1] - position).clamp(-self.radius, self.radius))
        return self.gravity, torch.cat([lower, upper], dim=1)

    def encode(self, velocity_history: Tensor, particle_type: Tensor, gravity: Tensor, walls: Tensor) -> Tensor:
        """``h^0`` from invariants only.

        Shapes:
            velocity_history ``[N, k, D]``, gravity ``[D]`` or ``[N, D]``, walls ``[N, W, D]`` -> ``[N, C]``
        """
        g = (gravity / self.acceleration_scale).expand(velocity_history.size(0), -1).unsqueeze(1)  # [N, 1, D]
        velocity = velocity_history / self.velocity_scale  # [N, k, D]
        walls = walls / self.radius  # [N, W, D], length <= 1
        invariants = [smooth_norm(velocity), (velocity * g).sum(-1),  # [N, k] each
                      smooth_norm(walls), (walls * g).sum(-1),  # [N, W] each
                      self.type_embedding(particle_type)]
        return self.encoder(torch.cat(invariants, dim=-1))

    def predict(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor, edge_index: Tensor,
                gravity: Tensor, walls: Tensor) -> Tensor:
        """``v^{t+1}`` from the state and the named vectors given explicitly (rotate them with the
        scene and the prediction rotates with it).

        Shapes:
            position ``[N, D]``, velocity_history ``[N, k, D]``, particle_type ``[N]``,
            edge_index ``[2, E]``, gravity ``[D]`` or ``[N, D]`` (per frame^2), walls ``[N, 2 D, D]``
            (position units)  ->  ``[N, D]``
        """
        h = self.encode(velocity_history, particle_type, gravity, walls)  # [N, C]
        sender, receiver = edge_index
        edge_vector = (position[receiver] - position[sender]) / self.radius  # [E, D], x_i - x_j at p^t
        walls, g = walls / self.radius, gravity / self.acceleration_scale
        velocity = velocity_history[:, -1] / self.radius  # [N, D], v^t in R per frame
        scale = self.acceleration_scale / self.radius
        kinematic = (particle_type == KINEMATIC).unsqueeze(-1)
        x = torch.zeros_like(velocity)  # [N, D], displacement since p^t
        for layer in self.processor:
            h, u = layer(h, x, velocity, edge_index, edge_vector, walls, g, scale)
            u = torch.where(kinematic, velocity, u)
            x = x + u / len(self.processor)  # the layers as substeps of one frame
        return x * self.radius  # p^{t+1} - p^t = v^{t+1}  (dt = 1)

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        gravity, walls = self.vector_inputs(position)
        return self.predict(position, velocity_history, particle_type, edge_index, gravity, walls)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", layers={len(self.processor)}"
