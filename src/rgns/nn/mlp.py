"""The multilayer perceptron every GNS-family block is built from."""
from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F


def mlp(in_channels: int, hidden_channels: int, out_channels: int, hidden_layers: int = 2,
        layer_norm: bool = True) -> nn.Sequential:
    """``hidden_layers`` ReLU layers of width ``hidden_channels``, a linear output, and an optional
    LayerNorm on the output (GNS puts one on every MLP but the decoder's).

    Shapes:
        ``[*, in_channels]``  ->  ``[*, out_channels]``
    """
    layers: list[nn.Module] = []
    width = in_channels
    for _ in range(hidden_layers):
        layers += [nn.Linear(width, hidden_channels), nn.ReLU(inplace=True)]
        width = hidden_channels
    layers.append(nn.Linear(width, out_channels))
    if layer_norm:
        layers.append(nn.LayerNorm(out_channels))
    return nn.Sequential(*layers)


def last_linear(module: nn.Sequential) -> nn.Linear:
    """The output ``nn.Linear`` of an :func:`mlp`."""
    return [layer for layer in module if isinstance(layer, nn.Linear)][-1]


def edge_input_terms(edge_mlp: nn.Sequential, channels: int, x: Tensor, edge_attr: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    r"""The first layer of an edge MLP defined on :math:`[\mathbf{e}_{ij}, \mathbf{h}_i, \mathbf{h}_j]`
    (edge, receiver, sender; ``channels`` wide each), split into its three terms: the edge term
    :math:`W_e \mathbf{e}_{ij} + b` and the receiver and sender terms computed on the nodes, to be
    gathered to the edges and summed (``edge_mlp[1:]`` then finishes the MLP). The same function
    as the layer on the concatenation, with the node terms computed once per node, not per edge.

    Shapes:
        ``x [N, channels]``, ``edge_attr [E, channels]``  ->  ``[E, H]``, ``[N, H]``, ``[N, H]``
    """
    first = edge_mlp[0]
    edge_term = F.linear(edge_attr, first.weight[:, :channels], first.bias)
    node_weight = first.weight[:, channels:]  # [H, 2 channels]: receiver, sender
    receiver, sender = F.linear(x, torch.cat(node_weight.chunk(2, dim=1))).chunk(2, dim=1)
    return edge_term, receiver, sender
