r"""Continuous convolutions on particles (Ummenhofer et al. 2020) and DMCF's antisymmetric variant
(Prantl et al. 2022), in plain torch.

A continuous convolution of radius R looks its filter up in a grid of ``K^D`` learned matrices,
at the neighbour's offset mapped from the ball to the cube:

.. math::
    \mathbf{o}_i = \sum_{j:\ |\mathbf r_{ij}| < R} a\!\left(\tfrac{|\mathbf r_{ij}|^2}{R^2}\right)
        \mathbf{f}_j\, G\!\left(\Lambda\!\left(\tfrac{\mathbf r_{ij}}{R}\right)\right)
        + \mathrm{Dense}(\mathbf f_i),
    \qquad \mathbf r_{ij} = \mathbf x_j - \mathbf x_i,

with the window :math:`a(q) = \max(1 - q, 0)^3`, :math:`\Lambda` the volume-preserving map of the
unit ball onto the cube :math:`[-1, 1]^D` and :math:`G` read by (bi/tri)linear interpolation
between the grid's nodes, the outer nodes on the cube's faces. The lookup of an edge (its window,
the :math:`2^D` grid nodes around it and their weights) depends only on the geometry, so it is
computed once per step (:func:`neighbourhood`) and shared by every layer.

A layer is computed as "scatter, then multiply": each edge adds its window- and
interpolation-weighted sender features into the :math:`2^D` cells of its receiver
(``[N, K^D, C_in]``), and one matrix product with the flattened grid (``[K^D C_in, C_out]``)
gives every output; no per-edge matrix is ever formed.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn


def window(q: Tensor) -> Tensor:
    """Ummenhofer et al.'s window ``a(q) = max(1 - q, 0)^3`` of the squared distance ``q = |r|^2 / R^2``."""
    return (1.0 - q).clamp_min(0.0).pow(3)


def disc_to_square(x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """The area-preserving map of the unit disc onto ``[-1, 1]^2`` (the inverse of Shirley and
    Chiu's concentric map): the radius becomes the larger coordinate, the angle in each quadrant
    sector the smaller one linearly. Odd: ``(-x, -y) -> -(x, y)``; the Jacobian is ``4 / pi``."""
    horizontal = x.abs() >= y.abs()  # the sector |angle| <= pi / 4 around the x axis (or its opposite)
    major, minor = torch.where(horizontal, x, y), torch.where(horizontal, y, x)
    origin = major == 0  # then minor is 0 too
    major = torch.where(origin, torch.ones_like(major), major)  # keep atan2 and the norm differentiable
    sign = major.sign()
    big = sign * torch.sqrt(major * major + minor * minor)
    small = big * (4.0 / math.pi) * torch.atan2(sign * minor, major.abs())  # atan(minor / major)
    big, small = torch.where(origin, 0.0, big), torch.where(origin, 0.0, small)
    return torch.where(horizontal, big, small), torch.where(horizontal, small, big)


def ball_to_cylinder(x: Tensor, y: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The volume-preserving map of the unit ball onto the cylinder of radius 1 and height
    ``[-1, 1]`` along z (Griepentrog et al.): the two polar caps ``5/4 z^2 > x^2 + y^2`` become the
    end discs' neighbourhoods, the rest the mantle's. Odd; the Jacobian is ``3 / 2``."""
    planar = x * x + y * y
    norm = torch.sqrt(planar + z * z)
    cap = 1.25 * z * z > planar
    origin = norm == 0
    safe_norm = torch.where(origin, torch.ones_like(norm), norm)
    safe_planar = torch.where(cap | origin, torch.ones_like(planar), planar)  # the mantle has x, y != 0
    scale = torch.where(cap, torch.sqrt(3.0 * safe_norm / (safe_norm + z.abs())), safe_norm / torch.sqrt(safe_planar))
    height = torch.where(cap, torch.copysign(norm, z), 1.5 * z)
    scale = torch.where(origin, 0.0, scale)
    return x * scale, y * scale, height


def ball_to_cube(r: Tensor) -> Tensor:
    """The volume-preserving map Λ of the unit ball onto ``[-1, 1]^D`` (2D: the disc onto the
    square; 3D: the ball onto a cylinder along the last axis, then each of its discs onto a square).

    Shapes:
        r: ``[*, D]`` with ``|r| <= 1``  ->  ``[*, D]`` in ``[-1, 1]^D``
    """
    if r.shape[-1] == 2:
        return torch.stack(disc_to_square(r[..., 0], r[..., 1]), dim=-1)
    if r.shape[-1] == 3:
        x, y, z = ball_to_cylinder(r[..., 0], r[..., 1], r[..., 2])
        return torch.stack([*disc_to_square(x, y), z], dim=-1)
    raise ValueError(f"ball_to_cube is defined in 2D and 3D, got D={r.shape[-1]}")


@dataclass
class Neighbourhood:
    """The lookups of a continuous convolution on one set of edges (messages flow sender -> receiver).

    ``window [E]``: ``a(|r_ij|^2 / R^2)``; ``cell [E, 2^D]``: the flat grid index of each of the
    :math:`2^D` grid nodes around ``Λ(r_ij / R)``; ``weight [E, 2^D]``: their interpolation
    weights (summing to one); ``num_nodes``: the receivers' count.
    """

    sender: Tensor  # [E]
    receiver: Tensor  # [E]
    window: Tensor  # [E]
    cell: Tensor  # [E, 2^D]
    weight: Tensor  # [E, 2^D]
    num_nodes: int
    kernel_size: int

    @property
    def dim(self) -> int:
        return self.cell.size(1).bit_length() - 1  # 2^D corners

    def subset(self, mask: Tensor) -> "Neighbourhood":
        """The edges where ``mask [E]`` is true."""
        return Neighbourhood(self.sender[mask], self.receiver[mask], self.window[mask], self.cell[mask],
                             self.weight[mask], self.num_nodes, self.kernel_size)

    def aggregate(self, edge_features: Tensor) -> Tensor:
        """``sum_j a_ij w_ij,c f_ij`` per receiver i and grid node c.

        Shapes:
            edge_features: ``[E, C]``  ->  ``[N, K^D, C]``
        """
        num_cells = self.kernel_size ** self.dim
        weighted = (self.window.unsqueeze(-1) * self.weight).unsqueeze(-1) * edge_features.unsqueeze(1)  # [E, 2^D, C]
        index = (self.receiver.unsqueeze(-1) * num_cells + self.cell).flatten()  # [E 2^D]
        out = edge_features.new_zeros(self.num_nodes * num_cells, edge_features.size(-1))
        out.index_add_(0, index, weighted.flatten(0, 1))
        return out.view(self.num_nodes, num_cells, -1)


def neighbourhood(position: Tensor, edge_index: Tensor, radius: float, kernel_size: int) -> Neighbourhood:
    """The window and kernel lookups of every edge ``j -> i`` (``edge_index = [sender; receiver]``),
    differentiable in ``position``.

    The offset ``r_ij / R`` is mapped into the cube and then onto grid coordinates
    ``(u + 1) / 2 (K - 1)`` (the outer nodes on the faces); each coordinate is clamped to the grid
    and interpolated linearly between its two nodes.

    Shapes:
        position: ``[N, D]``, edge_index: ``[2, E]``  ->  :class:`Neighbourhood` of ``E`` edges
    """
    sender, receiver = edge_index
    offset = (position[sender] - position[receiver]) / radius  # [E, D], r_ij / R
    dim = offset.size(-1)
    grid = (ball_to_cube(offset) + 1.0) * (0.5 * (kernel_size - 1))  # [E, D] in [0, K - 1]
    grid = grid.clamp(0.0, kernel_size - 1)
    lower = grid.detach().floor().clamp(0, kernel_size - 2)  # the node below, so the one above exists
    fraction = grid - lower  # [E, D] in [0, 1]
    lower = lower.long()
    strides = [kernel_size ** (dim - 1 - d) for d in range(dim)]  # row-major flat index of a node
    cells, weights = [], []
    for corner in itertools.product((0, 1), repeat=dim):
        cell, weight = 0, 1.0
        for d, up in enumerate(corner):
            cell = cell + (lower[:, d] + up) * strides[d]
            weight = weight * (fraction[:, d] if up else 1.0 - fraction[:, d])
        cells.append(cell)
        weights.append(weight)
    return Neighbourhood(sender, receiver, window(offset.pow(2).sum(-1)), torch.stack(cells, dim=1),
                         torch.stack(weights, dim=1), position.size(0), kernel_size)


def kernel_grid(in_channels: int, out_channels: int, dim: int, kernel_size: int, first_axis: int | None = None) -> nn.Parameter:
    """A grid of ``K^D`` matrices ``[K, .., K, C_in, C_out]`` (``first_axis`` nodes along the first
    axis if given), uniform in ``+-0.5 / sqrt(C_in)``: about unit gain for the 10-40 neighbours a
    window of the usual radius holds (sum of a^2 over a uniform disc: ~ neighbours / 7)."""
    shape = (first_axis or kernel_size,) + (kernel_size,) * (dim - 1) + (in_channels, out_channels)
    bound = 0.5 / math.sqrt(in_channels)
    return nn.Parameter(torch.empty(shape).uniform_(-bound, bound))


class ContinuousConv(nn.Module):
    r"""A continuous convolution :math:`\mathbf o_i = \sum_j a_{ij} \mathbf f_j G(\Lambda(\mathbf r_{ij}/R))`
    plus a dense self term :math:`W \mathbf f_i + \mathbf b` (or a bias alone with ``dense=False``).

    Args:
        in_channels, out_channels (int): feature widths.
        dim (int): 2 or 3.
        kernel_size (int, optional): K, grid nodes per axis. (default: :obj:`8`)
        dense (bool, optional): add the dense self term (else a bias only). (default: :obj:`True`)

    Shapes:
        x: ``[N, C_in]`` (senders and receivers: the same particles), neighbourhood: ``E`` edges
        ->  ``[N, C_out]``
    """

    def __init__(self, in_channels: int, out_channels: int, dim: int, kernel_size: int = 8, dense: bool = True):
        super().__init__()
        self.in_channels, self.out_channels, self.dim, self.kernel_size = in_channels, out_channels, dim, kernel_size
        self.kernel = kernel_grid(in_channels, out_channels, dim, kernel_size)
        self.dense = nn.Linear(in_channels, out_channels) if dense else None
        self.bias = None if dense else nn.Parameter(torch.zeros(out_channels))

    def grid(self) -> Tensor:
        """The kernel grid as ``[K^D, C_in, C_out]``, row-major over the grid axes."""
        return self.kernel.reshape(-1, self.in_channels, self.out_channels)

    def forward(self, x: Tensor, neighbourhood: Neighbourhood) -> Tensor:
        gathered = neighbourhood.aggregate(x[neighbourhood.sender])  # [N, K^D, C_in]
        out = gathered.flatten(1) @ self.grid().flatten(0, 1)  # [N, C_out]
        return out + (self.dense(x) if self.dense is not None else self.bias)

    def extra_repr(self) -> str:
        return (f"{self.in_channels}, {self.out_channels}, dim={self.dim}, kernel_size={self.kernel_size}, "
                f"dense={self.dense is not None}")


class AntisymmetricConv(nn.Module):
    r"""DMCF's momentum-conserving layer: :math:`\mathbf o_i = \sum_j a_{ij} (\mathbf f_i + \mathbf f_j)
    W(\mathbf r_{ij})` with an odd kernel :math:`W(-\mathbf r) = -W(\mathbf r)`, no self term, no bias.

    A pair (i, j) adds :math:`a (\mathbf f_i + \mathbf f_j) W(\mathbf r_{ij})` to i and
    :math:`a (\mathbf f_j + \mathbf f_i) W(-\mathbf r_{ij})`, its negative, to j: the outputs over
    a symmetric neighbourhood sum to zero (Newton's third law: exact momentum conservation).
    The kernel is odd by construction: only the upper half of the grid along the first axis is
    learned, the lower half is its point reflection negated, ``G[K-1-a, K-1-b, ..] = -G[a, b, ..]``.
    Λ is odd and the lookup symmetric, so :math:`W(-\mathbf r) = -W(\mathbf r)` holds at every
    offset, not only on the nodes.

    Args:
        in_channels, out_channels, dim, kernel_size: as :class:`ContinuousConv` (K even).

    Shapes:
        x: ``[N, C_in]``, neighbourhood: ``E`` edges, symmetric (``j -> i`` with ``i -> j``)
        ->  ``[N, C_out]``, summing to zero over the N particles
    """

    def __init__(self, in_channels: int, out_channels: int, dim: int, kernel_size: int = 8):
        super().__init__()
        if kernel_size % 2:
            raise ValueError(f"the antisymmetric kernel needs an even kernel_size, got {kernel_size}")
        self.in_channels, self.out_channels, self.dim, self.kernel_size = in_channels, out_channels, dim, kernel_size
        self.half_kernel = kernel_grid(in_channels, out_channels, dim, kernel_size, first_axis=kernel_size // 2)

    def grid(self) -> Tensor:
        """The odd kernel grid as ``[K^D, C_in, C_out]``."""
        spatial = tuple(range(self.dim))
        full = torch.cat([-self.half_kernel.flip(spatial), self.half_kernel], dim=0)  # G(-u) = -G(u)
        return full.reshape(-1, self.in_channels, self.out_channels)

    def forward(self, x: Tensor, neighbourhood: Neighbourhood) -> Tensor:
        pair = x[neighbourhood.receiver] + x[neighbourhood.sender]  # [E, C_in], f_i + f_j: symmetric in the pair
        gathered = neighbourhood.aggregate(pair)  # [N, K^D, C_in]
        return gathered.flatten(1) @ self.grid().flatten(0, 1)  # [N, C_out]

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, dim={self.dim}, kernel_size={self.kernel_size}"
