"""The multilayer perceptron every GNS-family block is built from."""
from __future__ import annotations

from typing import Callable, TypeVar

import torch
from torch import Tensor, nn
from torch.nn import functional as F

T = TypeVar("T")


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


def split_first_layer(first: nn.Linear, edge_channels: int, edge_first: bool = True) -> tuple[Tensor, Tensor, Tensor]:
    r"""The first layer of an edge MLP on :math:`[\mathbf{e}_{ij}, \mathbf{h}_i, \mathbf{h}_j]`
    (``edge_channels`` wide, then two node latents of equal width; with ``edge_first=False``,
    :math:`[\mathbf{h}_i, \mathbf{h}_j, \mathbf{e}_{ij}]`) as the weights of its terms: the edge
    weight :math:`W_e`, and the receiver and sender weights stacked with the bias on the
    receiver's rows, so that one ``F.linear`` of the node latents gives
    :math:`[W_r \mathbf{h} + b, W_s \mathbf{h}]` (the node terms, computed once per node) and
    :func:`gathered_linear` finishes the layer on the edges.

    Shapes:
        ``first.weight [H, edge_channels + 2 C]``  ->  ``[H, edge_channels]``, ``[2 H, C]``, ``[2 H]``
    """
    node_channels = first.in_features - edge_channels
    if edge_first:
        edge_weight, node_weight = first.weight.split([edge_channels, node_channels], dim=1)
    else:
        node_weight, edge_weight = first.weight.split([node_channels, edge_channels], dim=1)
    node_weight = torch.cat(node_weight.chunk(2, dim=1))  # [2 H, C]: receiver rows, then sender rows
    node_bias = torch.cat([first.bias, torch.zeros_like(first.bias)])  # [2 H]
    return edge_weight, node_weight, node_bias


def gathered_linear(receiver_i: Tensor, sender_j: Tensor, edge_attr: Tensor, edge_weight: Tensor) -> Tensor:
    r""":math:`(W_r \mathbf{h} + b)_i + (W_s \mathbf{h})_j + W_e \mathbf{e}_{ij}`: the first layer
    of an edge MLP from its node terms gathered to the edges (:func:`split_first_layer`), the edge
    term accumulated in place by the matrix product (no bias copied to a fresh output, no
    separate sum).

    Shapes:
        ``receiver_i [E, H]``, ``sender_j [E, H]``, ``edge_attr [E, F]``, ``edge_weight [H, F]``  ->  ``[E, H]``
    """
    hidden = receiver_i + sender_j
    return hidden.addmm_(edge_attr.to(hidden.dtype), edge_weight.t().to(hidden.dtype))  # the dtype autocast gave


def memoised(owner: nn.Module, name: str, compute: Callable[[], T], *inputs: Tensor | None) -> T:
    """``compute()``, a function of ``inputs`` alone (parameters, buffers, small tensors derived
    from them), reused while no gradient is recorded and ``inputs`` hold the values it was last
    computed from (compared in full, so a changed, reloaded or moved weight computes it again).
    Kept in ``owner.__dict__``, not in its ``state_dict``. With gradients, or compiling, it is
    always computed: the value must be part of the graph. Computed outside any autocast, in the
    inputs' own precision, since the value outlives the context it was asked for in.
    """
    if torch.is_grad_enabled() or torch.compiler.is_compiling():
        return compute()
    memo = owner.__dict__.setdefault("_memo", {})
    seen = memo.get(name)
    if seen is not None and len(seen[0]) == len(inputs) and all(map(_same, seen[0], inputs)):
        return seen[1]
    device = next(t.device.type for t in inputs if t is not None)
    with torch.autocast(device, enabled=False):
        value = compute()
    memo[name] = ([None if t is None else t.detach().clone() for t in inputs], value)
    return value


def _same(a: Tensor | None, b: Tensor | None) -> bool:
    if a is None or b is None:
        return a is b
    return a.shape == b.shape and a.dtype == b.dtype and a.device == b.device and torch.equal(a, b)
