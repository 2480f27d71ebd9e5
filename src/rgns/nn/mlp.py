"""The multilayer perceptron every GNS-family block is built from."""
from __future__ import annotations

from torch import nn


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
