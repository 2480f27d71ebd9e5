"""Residual Reversible Message Passing (RRMP): R-GNS's processor.

Each of the M layers is a RevNet additive coupling over the two halves of the node latent,

    n_1' = n_1 + f(n_2 | graph),    n_2' = n_2 + g(n_1' | graph),

inverted exactly by subtraction in the opposite order. The coupling, its inverse and the
memory-saving backward (inputs freed in the forward pass, recomputed from the outputs in the
backward pass) are ``torch_geometric.nn.GroupAddRev`` with two groups; this module only supplies
the message-passing functions f and g and the conditions they read.

Conditions never change inside a step, so the inverse exists: the edge latent (``[E, C]``, the
encoded edge features, split by GroupAddRev into ``e_1`` for f and ``e_2`` for g as in the
paper's Eq. 5) and the node conditions (``[N, C_cond]``, given whole to f and g; their width must
differ from C, or GroupAddRev would split them too).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn
from torch_geometric.nn import GroupAddRev, MessagePassing

from rgns.nn.mlp import last_linear, mlp


class Coupling(MessagePassing):
    r"""A coupling function :math:`f` (or :math:`g`) of RRMP: message passing on one half of the
    node latent, conditioned on fixed edge latents and node conditions,

    .. math::
        f(\mathbf{h})_i = f^n\big(\mathbf{h}_i, \mathbf{c}_i, \textstyle\sum_{j \in \mathcal{N}(i)}
        f^e(\mathbf{e}_{ij}, \mathbf{h}_i, \mathbf{h}_j)\big)

    :math:`f^e` is layer-normalised like GNS's edge MLP; :math:`f^n` is not, and with
    ``zero_init`` its output layer starts at zero, so the coupling starts as the identity map
    (for R-GNS: constant-velocity extrapolation).

    Args:
        channels (int): width :math:`H` of the half latent (and of the edge latent it reads).
        condition_channels (int): width of the node conditions.
        hidden_channels (int, optional): width of the MLPs' hidden layers. (default: ``channels``)
        hidden_layers (int, optional): hidden layers of each MLP. (default: :obj:`2`)
        zero_init (bool, optional): start :math:`f^n`'s output layer at zero. (default: :obj:`True`)

    Shapes:
        - **input:** half latent :math:`(|\mathcal{V}|, H)`, edge indices :math:`(2, |\mathcal{E}|)`,
          edge latents :math:`(|\mathcal{E}|, H)`, node conditions :math:`(|\mathcal{V}|, C_{cond})`
        - **output:** :math:`(|\mathcal{V}|, H)`, the increment added to the other half
    """

    def __init__(self, channels: int, condition_channels: int, hidden_channels: int | None = None,
                 hidden_layers: int = 2, zero_init: bool = True):
        super().__init__(aggr="sum")
        hidden_channels = hidden_channels or channels
        self.zero_init = zero_init
        self.edge_mlp = mlp(3 * channels, hidden_channels, channels, hidden_layers)
        self.node_mlp = mlp(2 * channels + condition_channels, hidden_channels, channels, hidden_layers,
                            layer_norm=False)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        super().reset_parameters()
        for module in self.modules():
            if isinstance(module, (nn.Linear, nn.LayerNorm)):
                module.reset_parameters()
        if self.zero_init:
            nn.init.zeros_(last_linear(self.node_mlp).weight)
            nn.init.zeros_(last_linear(self.node_mlp).bias)

    def forward(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor, condition: Tensor) -> Tensor:
        message = self.edge_updater(edge_index, x=x, edge_attr=edge_attr)  # [E, H]
        aggregated = self.propagate(edge_index, message=message, size=(x.size(0), x.size(0)))  # [N, H]
        return self.node_mlp(torch.cat([x, condition, aggregated], dim=-1))

    def edge_update(self, x_i: Tensor, x_j: Tensor, edge_attr: Tensor) -> Tensor:
        return self.edge_mlp(torch.cat([edge_attr, x_i, x_j], dim=-1))

    def message(self, message: Tensor) -> Tensor:
        return message


class RRMP(nn.Module):
    r"""Residual Reversible Message Passing: ``layers`` two-group
    :class:`torch_geometric.nn.GroupAddRev` blocks over :class:`Coupling` functions.

    ``forward`` maps the latent of frame t to that of t+1, ``inverse`` maps it back; both are
    exact up to float rounding. With ``memory_saving`` (the default) and gradients enabled, each
    block frees its input and recomputes it from its output in the backward pass, so training
    memory does not grow with depth; the latent passed in is freed (clone it if you still need
    it). Without gradients (rollouts, evaluation) the blocks run plainly.

    ``edges="updated"`` (ablation) gives block l its own edge latent
    :math:`\mathbf{e}^l = \mathbf{e}^{l-1} + u^l(\mathbf{e}^{l-1})`, a function of the fixed edge
    latent only, so the inverse still exists; ``edges="fixed"`` (the paper's) shares one.

    Args:
        channels (int): latent width :math:`C` (even; split into two halves).
        layers (int): number of reversible blocks :math:`M`.
        condition_channels (int): width of the node conditions (must differ from :math:`C`).
        hidden_channels (int, optional): MLP hidden width. (default: :math:`C/2`)
        hidden_layers (int, optional): hidden layers of each MLP. (default: :obj:`2`)
        edges (str, optional): ``"fixed"`` or ``"updated"``. (default: ``"fixed"``)
        memory_saving (bool, optional): use GroupAddRev's memory-saving backward when gradients
            are enabled. (default: :obj:`True`)
        zero_init (bool, optional): start every block as the identity. (default: :obj:`True`)

    Shapes:
        - **input:** node latents :math:`(|\mathcal{V}|, C)`, edge indices :math:`(2, |\mathcal{E}|)`,
          edge latents :math:`(|\mathcal{E}|, C)`, node conditions :math:`(|\mathcal{V}|, C_{cond})`
        - **output:** node latents :math:`(|\mathcal{V}|, C)`
    """

    def __init__(self, channels: int, layers: int, condition_channels: int, hidden_channels: int | None = None,
                 hidden_layers: int = 2, edges: str = "fixed", memory_saving: bool = True, zero_init: bool = True):
        super().__init__()
        if channels % 2:
            raise ValueError(f"RRMP splits the latent in two halves; channels must be even, got {channels}")
        if condition_channels == channels:
            raise ValueError(f"node conditions of width {condition_channels} equal the latent width: "
                             "GroupAddRev would split them between f and g; choose another latent width")
        if edges not in ("fixed", "updated"):
            raise ValueError(f"edges must be 'fixed' or 'updated', got {edges!r}")
        half = channels // 2
        hidden_channels = hidden_channels or half
        self.memory_saving = memory_saving
        self.blocks = nn.ModuleList(
            GroupAddRev(nn.ModuleList([
                Coupling(half, condition_channels, hidden_channels, hidden_layers, zero_init)  # f, then g
                for _ in range(2)
            ]))
            for _ in range(layers)
        )
        self.edge_updates = (nn.ModuleList(mlp(channels, channels, channels, hidden_layers) for _ in range(layers))
                             if edges == "updated" else None)

    def edge_latents(self, edge_attr: Tensor) -> list[Tensor]:
        """The edge latent each block reads: the same for all (fixed) or updated per block."""
        if self.edge_updates is None:
            return [edge_attr] * len(self.blocks)
        latents = []
        for update in self.edge_updates:
            edge_attr = edge_attr + update(edge_attr)  # depends on the conditions only
            latents.append(edge_attr)
        return latents

    def _set_memory_saving(self) -> None:
        plain = not (self.memory_saving and torch.is_grad_enabled())
        for block in self.blocks:
            block.disable = plain

    def forward(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor, condition: Tensor) -> Tensor:
        self._set_memory_saving()
        for block, edge_latent in zip(self.blocks, self.edge_latents(edge_attr)):
            x = block(x, edge_index, edge_latent, condition)
        return x

    def inverse(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor, condition: Tensor) -> Tensor:
        self._set_memory_saving()
        for block, edge_latent in zip(reversed(self.blocks), reversed(self.edge_latents(edge_attr))):
            x = block.inverse(x, edge_index, edge_latent, condition)
        return x
