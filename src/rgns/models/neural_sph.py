"""Neural SPH (Toshev et al. 2024): GNS with the external force taken out of what it learns, and
SPH relaxation of the particles after every learned step of a rollout.

- External force: the network predicts the acceleration minus gravity; the integrator adds
  gravity back, ``v^{t+1} = v^t + (a_net + g)`` (dt = 1, ``g`` per frame squared). The target's
  normalisation statistics are those of ``a - g``: the mean shifts by ``g``, the std is unchanged.
- Relaxation (inference only): after the learned step, the fluid particles are moved down the
  gradient of an SPH pressure computed from their density, a few small steps, which evens out
  the clusters and voids a learned step leaves behind. The settings are the paper's, in its units:
  particle spacing ``dx = 1``, rest density ``rho_0 = 1``, particle mass ``m = rho_0 dx^D = 1``.
  Positions are divided by the dataset's spacing before and the shift multiplied by it after, so
  the settings carry over unchanged to a dataset in metres.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace

import torch
from torch import Tensor, nn

from rgns.data.contract import KINEMATIC
from rgns.data.graph import NeighbourList, batched_radius_graph
from rgns.models.base import State, dataset_gravity
from rgns.models.gns import GNS

# sigma_D of the quintic spline (Morris et al. 1997) with h = 1: the kernel integrates to 1
QUINTIC_NORMALISATION = {1: 1.0 / 120.0, 2: 7.0 / (478.0 * math.pi), 3: 1.0 / (120.0 * math.pi)}
QUINTIC_SUPPORT = 3.0  # the kernel vanishes beyond 3 h
DEFAULT_SPACING = 0.0065  # the default scene's (conf/scene/waterdrop.yaml), for data that carries none


def quintic_kernel(q: Tensor, dim: int) -> Tensor:
    """The quintic spline ``W(q)`` at ``q = r / h``, with ``h = 1``. ``[*] -> [*]``"""
    terms = (3.0 - q).clamp(min=0) ** 5 - 6 * (2.0 - q).clamp(min=0) ** 5 + 15 * (1.0 - q).clamp(min=0) ** 5
    return QUINTIC_NORMALISATION[dim] * terms


def quintic_kernel_derivative(q: Tensor, dim: int) -> Tensor:
    """``dW/dq`` of :func:`quintic_kernel` (zero at ``q = 0``, negative inside the support). ``[*] -> [*]``"""
    terms = (3.0 - q).clamp(min=0) ** 4 - 6 * (2.0 - q).clamp(min=0) ** 4 + 15 * (1.0 - q).clamp(min=0) ** 4
    return -5 * QUINTIC_NORMALISATION[dim] * terms


class SPHRelaxation(nn.Module):
    """The relaxation of Neural SPH: ``loops`` steps ``r_i += step * a_i`` of the SPH pressure
    acceleration, in units of the particle spacing (``h = dx = 1``, ``rho_0 = 1``, ``m = 1``).

    - density ``rho_i = sum_j W(|r_ij|)`` over the particles within ``3 h``, the particle itself included;
    - free surface: densities below ``density_bounds[0]`` count as ``rho_0`` (no pull towards the
      surface from the particles that miss neighbours there), densities above
      ``density_bounds[1]`` are capped at it;
    - linear equation of state ``p = c_0^2 (rho - rho_0)``;
    - ``a_i = -(1/m) sum_j (V_i^2 + V_j^2) p_ij grad_i W_ij`` with ``V = m / rho`` and the
      density-weighted pair pressure ``p_ij = (rho_j p_i + rho_i p_j) / (rho_i + rho_j)`` (Adami et
      al. 2012): a compressed pair pushes apart along ``r_i - r_j``.

    Every particle counts in the densities; kinematic ones (type 3) are not moved.

    Args:
        dim (int): spatial dimension.
        spacing (float): the particle spacing ``dx``, in position units.
        loops (int, optional): relaxation steps. (default: :obj:`1`)
        step (float, optional): ``alpha``, the step size (dx per unit acceleration). (default: :obj:`0.015`)
        sound_speed (float, optional): ``c_0`` of the equation of state. (default: :obj:`10.0`)
        density_bounds (tuple, optional): the free-surface threshold and the cap. (default: :obj:`(0.98, 1.02)`)
    """

    def __init__(self, dim: int, spacing: float, loops: int = 1, step: float = 0.015, sound_speed: float = 10.0,
                 density_bounds: tuple[float, float] = (0.98, 1.02)):
        super().__init__()
        if spacing <= 0 or loops < 0 or not density_bounds[0] <= 1.0 <= density_bounds[1]:
            raise ValueError(f"relaxation needs spacing > 0 (got {spacing}), loops >= 0 (got {loops}) and "
                             f"density_bounds around the rest density 1 (got {tuple(density_bounds)})")
        self.dim, self.spacing, self.loops, self.step = dim, float(spacing), int(loops), float(step)
        self.sound_speed = float(sound_speed)
        self.density_bounds = (float(density_bounds[0]), float(density_bounds[1]))
        self.own_density = float(quintic_kernel(torch.zeros(()), dim))

    def density(self, x: Tensor, edge_index: Tensor) -> Tensor:
        """Kernel-summed density of positions ``x`` in units of the spacing.

        Shapes:
            x: ``[N, D]``, edge_index: ``[2, E]`` (pairs within 3 h)  ->  ``[N]``
        """
        sender, receiver = edge_index
        distance = (x[receiver] - x[sender]).norm(dim=-1)  # [E]
        own = x.new_full((len(x),), self.own_density)  # each particle's own share, W(0)
        return own.index_add(0, receiver, quintic_kernel(distance, self.dim))

    def pressure(self, density: Tensor) -> tuple[Tensor, Tensor]:
        """The free-surface treatment of the density, and the equation of state on it.

        Shapes:
            density: ``[N]``  ->  density ``[N]`` (treated), pressure ``[N]``
        """
        low, high = self.density_bounds
        # a particle that misses neighbours (at a free surface) counts as at rest, not under tension
        density = torch.where(density < low, torch.ones_like(density), density.clamp(max=high))
        return density, self.sound_speed**2 * (density - 1.0)

    def acceleration(self, x: Tensor, edge_index: Tensor) -> Tensor:
        """The pressure acceleration, in spacing units.

        Shapes:
            x: ``[N, D]``, edge_index: ``[2, E]``  ->  ``[N, D]``
        """
        density, pressure = self.pressure(self.density(x, edge_index))  # [N], [N]
        j, i = edge_index
        rho_i, rho_j = density[i], density[j]
        pair_pressure = (rho_j * pressure[i] + rho_i * pressure[j]) / (rho_i + rho_j)  # [E]
        r_ij = x[i] - x[j]  # [E, D]
        distance = r_ij.pow(2).sum(-1).clamp(min=1e-12).sqrt()  # safe to differentiate at coincidence
        grad_w = quintic_kernel_derivative(distance, self.dim).unsqueeze(-1) * r_ij / distance.unsqueeze(-1)
        volumes = rho_i.pow(-2) + rho_j.pow(-2)  # (m/rho_i)^2 + (m/rho_j)^2 with m = 1
        term = (volumes * pair_pressure).unsqueeze(-1) * grad_w  # [E, D]
        return -torch.zeros_like(x).index_add(0, i, term)  # divided by m = 1

    def forward(self, position: Tensor, particle_type: Tensor, batch: Tensor | None = None) -> Tensor:
        """Relaxed positions; kinematic particles' rows are returned untouched.

        Shapes:
            position: ``[N, D]`` (position units), particle_type: ``[N]``, batch: ``[N]``  ->  ``[N, D]``
        """
        moving = (particle_type != KINEMATIC).unsqueeze(-1)
        for _ in range(self.loops):
            x = position / self.spacing  # [N, D], spacing units
            edge_index = batched_radius_graph(x, QUINTIC_SUPPORT, batch)
            shift = self.step * self.acceleration(x, edge_index) * self.spacing  # back to position units
            position = torch.where(moving, position + shift, position)
        return position

    def extra_repr(self) -> str:
        return (f"spacing={self.spacing:g}, loops={self.loops}, step={self.step:g}, "
                f"sound_speed={self.sound_speed:g}, density_bounds={self.density_bounds}")


def dataset_spacing(metadata: dict, spacing: float | None = None) -> float:
    """The particle spacing ``dx``: ``spacing`` (given), else the generator's
    (``metadata["generator"]["params"]["spacing"]``), else :data:`DEFAULT_SPACING`."""
    if spacing is not None:
        return float(spacing)
    params = (metadata.get("generator") or {}).get("params")
    # a mapping as metadata.json holds it, or the scene object itself where Hydra's instantiate,
    # handed the metadata as an argument, has built the scene config it describes
    spacing = params.get("spacing") if isinstance(params, Mapping) else getattr(params, "spacing", None)
    return DEFAULT_SPACING if spacing is None else float(spacing)


class NeuralSPH(GNS):
    """GNS trained on the acceleration minus gravity, with SPH relaxation after each rollout step.

    The network is GNS's, unchanged (:class:`~rgns.models.gns.GNS`). :meth:`next_velocity` adds
    the external force back; :meth:`step` relaxes the fluid particles after the learned step in
    eval mode only, so training (one step, pushforward and unrolled windows alike) sees the bare
    network, as in the paper, and every rollout of a model in eval mode (validation, evaluation)
    sees the relaxation.

    The relaxation's shift enters the newest velocity: ``v^{t+1} = p^{t+1}_relaxed - p^t``, so
    that ``p^{t+1} = p^t + v^{t+1}`` holds and the next step reads the velocity the particles
    really had (the paper's model, whose state is a history of positions, does the same).

    Args:
        metadata, history, noise_std, latent, layers, hidden_layers, embedding, hard_walls: see
            :class:`~rgns.models.gns.GNS`; with ``hard_walls`` the relaxed position is kept in the box too.
        gravity (list, optional): gravity in m/s^2; ``None``: the dataset's (:func:`dataset_gravity`).
        spacing (float, optional): the particle spacing ``dx``; ``None``: the dataset's (:func:`dataset_spacing`).
        relaxation_loops (int, optional): relaxation steps after each learned step; 0: none. (default: :obj:`1`)
        relaxation_step (float, optional): ``alpha``. (default: :obj:`0.015`)
        sound_speed (float, optional): ``c_0``, in spacings per unit time. (default: :obj:`10.0`)
        density_bounds (tuple, optional): free-surface threshold and cap of the density. (default: :obj:`(0.98, 1.02)`)
    """

    display_name = "NeuralSPH"

    def __init__(self, metadata: dict, history: int = 5, noise_std: float = 6.7e-4, latent: int = 128,
                 layers: int = 10, hidden_layers: int = 2, embedding: int = 16, hard_walls: bool = False,
                 gravity: list[float] | None = None, spacing: float | None = None, relaxation_loops: int = 1,
                 relaxation_step: float = 0.015, sound_speed: float = 10.0,
                 density_bounds: tuple[float, float] = (0.98, 1.02)):
        super().__init__(metadata, history, noise_std, latent, layers, hidden_layers, embedding, hard_walls)
        self.register_buffer("gravity", dataset_gravity(metadata, gravity))  # [D], per frame^2
        self.acc_mean -= self.gravity  # the target is a - g: its mean shifts by g, its std does not
        self.relaxation = SPHRelaxation(self.dim, dataset_spacing(metadata, spacing), relaxation_loops,
                                        relaxation_step, sound_speed, tuple(density_bounds))

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        # GNS's velocity carries the network's acceleration, a - g: the integrator adds g back
        return super().next_velocity(position, velocity_history, particle_type, edge_index, batch) + self.gravity

    def step(self, state: State, kinematic_position: Tensor | None = None,
             neighbours: NeighbourList | None = None) -> State:
        """The learned step of :class:`~rgns.models.base.Simulator`, then (eval mode) the relaxation."""
        learned = super().step(state, kinematic_position, neighbours)
        if self.training or self.relaxation.loops == 0:
            return learned
        relaxed = self.relaxation(learned.position, state.particle_type, state.batch)  # [N, D]
        velocity = relaxed - state.position  # the step's velocity includes the relaxation's shift
        if self.hard_walls:
            velocity = self.stop_at_walls(state.position, velocity)
        kinematic = (state.particle_type == KINEMATIC).unsqueeze(-1)
        velocity = torch.where(kinematic, learned.velocity_history[:, -1], velocity)  # as the base class put them
        history = torch.cat([state.velocity_history[:, 1:], velocity.unsqueeze(1)], dim=1)  # [N, k, D]
        return replace(state, position=state.position + velocity, velocity_history=history)  # dt = 1
