"""Encoders/decoders between a node's physical features and its latent.

Both classes share one interface, ``encode(x) -> n`` and ``decode(n) -> x``, so R-GNS takes
either: the exactly invertible linear projection of the paper (ILP), or the MLP pair of its
ablation, whose decoder only learns to undo the encoder.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from rgns.nn.mlp import memoised, mlp


class ILP(nn.Module):
    r"""Invertible Linear Projection (R-GNS, Eq. 3):

    .. math::
        \mathbf{n} = W \mathbf{x} + B \quad \text{(encode)}, \qquad
        \mathbf{x} = W^{\dagger} (\mathbf{n} - B) \quad \text{(decode)}

    with :math:`W \in \mathbb{R}^{b \times a}`, :math:`b \geq a`, and :math:`W^{\dagger}` its
    Moore-Penrose pseudo-inverse (SVD; decode runs in float64 and follows the learned
    :math:`W`). ``decode(encode(x)) == x`` whenever :math:`W` has full column rank;
    ``encode(decode(n))`` is the projection of ``n`` onto the range of the encoder.
    :math:`W` starts semi-orthogonal, where :math:`W^{\dagger} = W^\top`.

    Args:
        in_channels (int): physical features per node :math:`a` (``history * dim`` in R-GNS).
        out_channels (int): latent width :math:`b`.

    Shapes:
        - **encode:** :math:`(*, a) \to (*, b)`
        - **decode:** :math:`(*, b) \to (*, a)`
    """

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        if out_channels < in_channels:
            raise ValueError(f"ILP needs out_channels >= in_channels to be invertible, got {out_channels} < {in_channels}")
        self.weight = nn.Parameter(torch.empty(out_channels, in_channels))
        self.bias = nn.Parameter(torch.zeros(out_channels))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        nn.init.orthogonal_(self.weight)
        nn.init.zeros_(self.bias)

    def pseudo_inverse(self) -> Tensor:
        """:math:`W^{\dagger}`, in float64.  ``[a, b]``"""
        return torch.linalg.pinv(self.weight.double())

    def encode(self, x: Tensor) -> Tensor:
        return nn.functional.linear(x, self.weight, self.bias)

    def decode(self, n: Tensor) -> Tensor:
        # in float64: the float32 rounding of n is then the only error of decode(encode(x))
        pseudo_inverse = memoised(self, "pseudo_inverse", self.pseudo_inverse, self.weight)  # one SVD per weight
        x = nn.functional.linear(n.double() - self.bias.double(), pseudo_inverse)
        return x.to(n.dtype)

    def extra_repr(self) -> str:
        return f"{self.weight.size(1)}, {self.weight.size(0)}"


class MLPEncoderDecoder(nn.Module):
    r"""The ablation's encoder/decoder: two independent MLPs (GNS-style, no LayerNorm), so
    ``decode(encode(x))`` equals ``x`` only as far as training makes it.

    Shapes:
        - **encode:** :math:`(*, a) \to (*, b)`
        - **decode:** :math:`(*, b) \to (*, a)`
    """

    def __init__(self, in_channels: int, out_channels: int, hidden_layers: int = 2):
        super().__init__()
        self.encoder = mlp(in_channels, out_channels, out_channels, hidden_layers, layer_norm=False)
        self.decoder = mlp(out_channels, out_channels, in_channels, hidden_layers, layer_norm=False)

    def encode(self, x: Tensor) -> Tensor:
        return self.encoder(x)

    def decode(self, n: Tensor) -> Tensor:
        return self.decoder(n)
