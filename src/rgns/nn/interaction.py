"""GNS's interaction network (Sanchez-Gonzalez et al. 2020; Battaglia et al. 2016)."""
from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F
from torch_geometric.nn import MessagePassing

from rgns.nn.mlp import gathered_linear, memoised, mlp, split_first_layer


class InteractionNetwork(MessagePassing):
    r"""One GNS processor step with residual edge and node updates:

    .. math::
        \mathbf{e}_{ij}' &= \mathbf{e}_{ij} + f^e(\mathbf{e}_{ij}, \mathbf{n}_i, \mathbf{n}_j)

        \mathbf{n}_i' &= \mathbf{n}_i + f^n\big(\mathbf{n}_i, \textstyle\sum_{j \in \mathcal{N}(i)}
        f^e(\mathbf{e}_{ij}, \mathbf{n}_i, \mathbf{n}_j)\big)

    where :math:`f^e` and :math:`f^n` are MLPs whose outputs are layer-normalised. The first
    layer of :math:`f^e`, linear in :math:`[\mathbf{e}_{ij}, \mathbf{n}_i, \mathbf{n}_j]`, is
    evaluated as :math:`W_e \mathbf{e}_{ij} + b + (W_r \mathbf{n})_i + (W_s \mathbf{n})_j`,
    the node terms on the nodes before they are gathered to the edges (the same function as
    the concatenation, with a third of its per-edge work; :func:`~rgns.nn.mlp.gathered_linear`).

    Args:
        channels (int): width of the node and edge latents.
        hidden_layers (int, optional): hidden layers of each MLP. (default: :obj:`2`)

    Shapes:
        - **input:** node latents :math:`(|\mathcal{V}|, C)`, edge indices :math:`(2, |\mathcal{E}|)`
          (senders in row 0, receivers in row 1), edge latents :math:`(|\mathcal{E}|, C)`
        - **output:** node latents :math:`(|\mathcal{V}|, C)`, edge latents :math:`(|\mathcal{E}|, C)`
    """

    def __init__(self, channels: int, hidden_layers: int = 2):
        super().__init__(aggr="sum")
        self.channels = channels
        self.edge_mlp = mlp(3 * channels, channels, channels, hidden_layers)
        self.node_mlp = mlp(2 * channels, channels, channels, hidden_layers)

    def forward(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor) -> tuple[Tensor, Tensor]:
        first = self.edge_mlp[0]
        edge_weight, node_weight, node_bias = memoised(
            self, "first_layer", lambda: split_first_layer(first, self.channels), first.weight, first.bias)
        receiver, sender = F.linear(x, node_weight, node_bias).chunk(2, dim=1)  # [N, C] each
        message = self.edge_updater(edge_index, receiver=receiver, sender=sender, edge_attr=edge_attr,
                                    edge_weight=edge_weight)  # [E, C]
        aggregated = self.propagate(edge_index, message=message, size=(x.size(0), x.size(0)))  # [N, C]
        x_new = x + self.node_mlp(torch.cat([x, aggregated], dim=-1))
        return x_new, edge_attr + message

    def edge_update(self, receiver_i: Tensor, sender_j: Tensor, edge_attr: Tensor, edge_weight: Tensor) -> Tensor:
        return self.edge_mlp[1:](gathered_linear(receiver_i, sender_j, edge_attr, edge_weight))

    def message(self, message: Tensor) -> Tensor:
        return message
