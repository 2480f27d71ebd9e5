"""The E(n)-equivariant graph convolution of Satorras, Hoogeboom and Welling (2021), in its
velocity form, with the walls of a box and gravity entering as named vectors."""
from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F
from torch_geometric.nn import MessagePassing
from torch_geometric.utils import degree

from rgns.nn.mlp import edge_input_terms

EPS = 1e-8  # inside every square root: |x|^2 + eps keeps gradients finite where vectors vanish


def silu_mlp(in_channels: int, hidden_channels: int, out_channels: int, final_activation: bool = False,
             bias: bool = True) -> nn.Sequential:
    """EGNN's two-layer MLPs: ``Linear, SiLU, Linear`` (and a final SiLU for the message MLPs).

    Shapes:
        ``[*, in_channels]``  ->  ``[*, out_channels]``
    """
    layers: list[nn.Module] = [nn.Linear(in_channels, hidden_channels), nn.SiLU(),
                               nn.Linear(hidden_channels, out_channels, bias=bias)]
    if final_activation:
        layers.append(nn.SiLU())
    return nn.Sequential(*layers)


def smooth_norm(vector: Tensor) -> Tensor:
    """``sqrt(|v|^2 + eps)`` over the last axis: a norm whose gradient is finite at ``v = 0``.  ``[*, D] -> [*]``"""
    return (vector.pow(2).sum(-1) + EPS).sqrt()


class EquivariantLayer(MessagePassing):
    r"""One E(n)-equivariant convolution (E-GCL, velocity form), with walls and gravity:

    .. math::
        \mathbf{m}_{ij} &= \phi_e(|\mathbf{x}_{ij}|^2, a_{ij}, \mathbf{h}_i, \mathbf{h}_j),
        \qquad \mathbf{x}_{ij} = \mathbf{x}_i - \mathbf{x}_j

        \mathbf{m}_{iw} &= \phi_{w}(|\mathbf{x}_{iw}|^2, a_{iw}, \mathbf{h}_i),
        \qquad \mathbf{x}_{iw} = \mathbf{x}_i - \mathbf{x}_w

        \mathbf{u}_i &= \phi_v(\mathbf{h}_i)\, \mathbf{v}_i + s \Big( C \sum_j \mathbf{x}_{ij}\,
        \phi_x(\mathbf{m}_{ij}) + \sum_w \mathbf{x}_{iw}\, \phi_{xw}(\mathbf{m}_{iw})
        + \phi_g(\mathbf{h}_i)\, \mathbf{g} \Big)

        \mathbf{h}_i' &= \mathbf{h}_i + \phi_h\big(\mathbf{h}_i, \textstyle\sum_j \mathbf{m}_{ij},
        \sum_w \mathbf{m}_{iw}\big)

    Each wall w is a virtual neighbour at a fixed point :math:`\mathbf{x}_w` (its point nearest
    to the particle at the start of the step, at most R away); :math:`\mathbf{g}` is gravity;
    the edge attributes :math:`a_{ij}`, :math:`a_{iw}` are the squared distances at the start of
    the step; s scales the vector terms (the acceleration's scale). Only vectors
    (:math:`\mathbf{x}_{ij}`, :math:`\mathbf{x}_{iw}`, :math:`\mathbf{v}_i`, :math:`\mathbf{g}`)
    are multiplied by the learned scalars, which see only invariants, so :math:`\mathbf{u}` rotates
    and reflects with the inputs. :math:`\phi_v = 1 + \psi_v`; the last layers of :math:`\phi_x`,
    :math:`\phi_{xw}`, :math:`\phi_g` and :math:`\psi_v` start at ``coordinate_gain`` times
    Xavier's (EGNN: 0.001), so a fresh layer returns ``u ~ v``.

    Positions are passed relative to the start of the step: ``x`` is each particle's displacement
    and ``edge_vector`` the fixed part of :math:`\mathbf{x}_{ij}` (the subtraction of two
    nearby absolute positions loses precision in float32; this does not).

    Args:
        channels (int): width of h and of the messages.
        coordinate_aggregation (str, optional): C, ``"mean"`` (over the neighbours, as EGNN's
            :math:`1/(M-1)`) or ``"sum"``. (default: :obj:`"mean"`)
        normalise (bool, optional): :math:`\mathbf{x}_{ij}` and :math:`\mathbf{x}_{iw}` as unit
            vectors in the coordinate sums (EGNN's ``normalize``). (default: :obj:`False`)
        tanh (bool, optional): bound :math:`\phi_x` and :math:`\phi_{xw}` to [-1, 1].
            (default: :obj:`False`)
        coordinate_gain (float, optional): Xavier gain of the last layers of the coordinate and
            gate MLPs. (default: :obj:`0.001`)
        update_features (bool, optional): compute :math:`\mathbf{h}'` (the last layer of a
            stack does not need it). (default: :obj:`True`)

    Shapes:
        - **input:** h :math:`(N, C)`, x :math:`(N, D)`, velocity :math:`(N, D)`, edge indices
          :math:`(2, E)` (senders j in row 0, receivers i in row 1), edge_vector :math:`(E, D)`
          (:math:`\mathbf{p}_i - \mathbf{p}_j`), walls :math:`(N, W, D)` (:math:`\mathbf{x}_w -
          \mathbf{p}_i`), gravity :math:`(D)` or :math:`(N, D)`
        - **output:** h' :math:`(N, C)`, u :math:`(N, D)`
    """

    def __init__(self, channels: int, coordinate_aggregation: str = "mean", normalise: bool = False,
                 tanh: bool = False, coordinate_gain: float = 1e-3, update_features: bool = True):
        super().__init__(aggr="sum")
        if coordinate_aggregation not in ("mean", "sum"):
            raise ValueError(f"coordinate_aggregation must be 'mean' or 'sum', not {coordinate_aggregation!r}")
        self.channels = channels
        self.coordinate_aggregation = coordinate_aggregation
        self.normalise, self.tanh = bool(normalise), bool(tanh)
        self.edge_mlp = silu_mlp(2 + 2 * channels, channels, channels, final_activation=True)  # phi_e
        self.wall_mlp = silu_mlp(2 + channels, channels, channels, final_activation=True)  # phi_w
        self.coordinate_mlp = silu_mlp(channels, channels, 1, bias=False)  # phi_x
        self.wall_coordinate_mlp = silu_mlp(channels, channels, 1, bias=False)  # phi_xw
        self.gravity_mlp = silu_mlp(channels, channels, 1)  # phi_g
        self.velocity_mlp = silu_mlp(channels, channels, 1)  # psi_v = phi_v - 1
        self.node_mlp = silu_mlp(3 * channels, channels, channels) if update_features else None  # phi_h
        for gate in (self.coordinate_mlp, self.wall_coordinate_mlp, self.gravity_mlp, self.velocity_mlp):
            nn.init.xavier_uniform_(gate[-1].weight, gain=coordinate_gain)
            if gate[-1].bias is not None:
                nn.init.zeros_(gate[-1].bias)

    def forward(self, h: Tensor, x: Tensor, velocity: Tensor, edge_index: Tensor, edge_vector: Tensor,
                walls: Tensor, gravity: Tensor, acceleration_scale: float | Tensor) -> tuple[Tensor, Tensor]:
        sender, receiver = edge_index
        relative = edge_vector + x[receiver] - x[sender]  # [E, D], x_ij now
        # squared distances: smooth where particles coincide; a_ij = |x_ij|^2 at the start of the step
        distances = torch.cat([relative.pow(2).sum(-1, keepdim=True), edge_vector.pow(2).sum(-1, keepdim=True)], dim=-1)
        # phi_e's first layer on [|x_ij|^2, a_ij, h_i, h_j], its node terms computed once per node
        edge_term, receiver_term, sender_term = edge_input_terms(self.edge_mlp, 2, h, distances)  # [E|N, C]
        # messages and coordinate terms of the neighbours, aggregated in one pass
        aggregated = self.propagate(edge_index, receiver=receiver_term, sender=sender_term, edge_term=edge_term,
                                    relative=relative, size=(h.size(0), h.size(0)))  # [N, C + D]
        message, pairs = aggregated[:, : self.channels], aggregated[:, self.channels :]  # [N, C], [N, D]
        if self.coordinate_aggregation == "mean":
            pairs = pairs / degree(edge_index[1], h.size(0), dtype=pairs.dtype).clamp(min=1).unsqueeze(-1)

        # the walls: virtual neighbours at fixed points, seen from the moved particle
        from_wall = x.unsqueeze(1) - walls  # [N, W, D], x_i - x_w
        wall_distances = torch.cat([from_wall.pow(2).sum(-1, keepdim=True), walls.pow(2).sum(-1, keepdim=True)], dim=-1)
        first = self.wall_mlp[0]  # on [|x_iw|^2, a_iw, h_i]: the h term once per node, not per wall
        wall_term = F.linear(wall_distances, first.weight[:, :2], first.bias) + F.linear(h, first.weight[:, 2:]).unsqueeze(1)
        wall_message = self.wall_mlp[1:](wall_term)  # [N, W, C]
        wall_weight = self.wall_coordinate_mlp(wall_message)  # [N, W, 1]
        if self.tanh:
            wall_weight = wall_weight.tanh()
        walls_term = (self._direction(from_wall) * wall_weight).sum(1)  # [N, D]

        gate = 1.0 + self.velocity_mlp(h)  # [N, 1], phi_v
        force = pairs + walls_term + self.gravity_mlp(h) * gravity  # [N, D], in units of the scale
        u = gate * velocity + acceleration_scale * force
        if self.node_mlp is not None:
            h = h + self.node_mlp(torch.cat([h, message, wall_message.sum(1)], dim=-1))
        return h, u

    def message(self, receiver_i: Tensor, sender_j: Tensor, edge_term: Tensor, relative: Tensor) -> Tensor:
        m = self.edge_mlp[1:](edge_term + receiver_i + sender_j)  # [E, C], m_ij
        weight = self.coordinate_mlp(m)  # [E, 1]
        if self.tanh:
            weight = weight.tanh()
        return torch.cat([m, self._direction(relative) * weight], dim=-1)  # [E, C + D]

    def _direction(self, vector: Tensor) -> Tensor:
        return vector / smooth_norm(vector).unsqueeze(-1) if self.normalise else vector

    def extra_repr(self) -> str:
        return (f"channels={self.channels}, coordinate_aggregation={self.coordinate_aggregation!r}, "
                f"normalise={self.normalise}, tanh={self.tanh}")
