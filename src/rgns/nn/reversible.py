"""Residual Reversible Message Passing (RRMP): R-GNS's processor.

Each of the M layers is a RevNet additive coupling over the two halves of the node latent,

    n_1' = n_1 + f(n_2 | graph),    n_2' = n_2 + g(n_1' | graph),

inverted exactly by subtraction in the opposite order. The coupling and its inverse are
``torch_geometric.nn.GroupAddRev`` with two groups; this module supplies the message-passing
functions f and g and the conditions they read, and gives GroupAddRev a cheaper memory-saving
backward (:class:`ReversibleBlock`).

Conditions never change inside a step, so the inverse exists: the edge latent (``[E, C]``, the
encoded edge features, split into ``e_1`` for f and ``e_2`` for g as in the paper's Eq. 5) and
the node conditions (``[N, C_cond]``, given whole to f and g; their width must differ from C, or
GroupAddRev would split them too). Both directions of a training step read the same edge
latent, so it is computed once for the two (``RGNS.both_velocities``).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F
from torch_geometric.nn import GroupAddRev, MessagePassing

from rgns.data.graph import wall_gate
from rgns.nn.mlp import gathered_linear, last_linear, memoised, mlp, split_first_layer


class Coupling(MessagePassing):
    r"""A coupling function :math:`f` (or :math:`g`) of RRMP: message passing on one half of the
    node latent, conditioned on fixed edge latents and node conditions,

    .. math::
        f(\mathbf{h})_i = f^n\big(\mathbf{h}_i, \mathbf{c}_i, \textstyle\sum_{j \in \mathcal{N}(i)}
        f^e(\mathbf{e}_{ij}, \mathbf{h}_i, \mathbf{h}_j)\big)

    :math:`f^e` and :math:`f^n` end in a LayerNorm, like GNS's MLPs: whatever the input, the
    increment a coupling adds is bounded by its LayerNorm's gain and bias (for R-GNS: so is the
    change of velocity in one step, as GNS's acceleration is bounded by its layer-normalised
    latents). With ``zero_init`` the gain and bias of :math:`f^n`'s LayerNorm start at zero
    (without ``node_norm``, its output layer), so the coupling starts as the identity map (for
    R-GNS: constant-velocity extrapolation).

    The first layer of :math:`f^e` is linear in the concatenation
    :math:`[\mathbf{e}_{ij}, \mathbf{h}_i, \mathbf{h}_j]`, so it is evaluated as
    :math:`W_e \mathbf{e}_{ij} + b + (W_r \mathbf{h})_i + (W_s \mathbf{h})_j`, the node terms on
    the nodes before they are gathered to the edges: the same function as the concatenation,
    with a third of its per-edge work.

    Args:
        channels (int): width :math:`H` of the half latent (and of the edge latent it reads).
        condition_channels (int): width of the node conditions.
        hidden_channels (int, optional): width of the MLPs' hidden layers. (default: ``channels``)
        hidden_layers (int, optional): hidden layers of each MLP. (default: :obj:`2`)
        zero_init (bool, optional): start :math:`f^n`'s output at zero. (default: :obj:`True`)
        node_norm (bool, optional): end :math:`f^n` in a LayerNorm (bounded increments).
            (default: :obj:`True`)
        pairwise (bool, optional): the increment is a sum of antisymmetrised pair terms plus a
            wall term,
            :math:`\sum_j \big(f^e(\mathbf{e}_{ij}, \mathbf{h}_i, \mathbf{h}_j) - f^e(\mathbf{e}_{ji}, \mathbf{h}_j, \mathbf{h}_i)\big)
            + w_i\, f^n(\mathbf{h}_i, \mathbf{c}_i)`, where :math:`w_i = 1 - \min` of the first
            ``wall_channels`` conditions (the wall distances over R, in [-1, 1]), clamped to
            [0, 1]: away from the walls the increments sum to zero over the particles.
            :math:`f^e` ends in a LayerNorm that starts at zero. (default: :obj:`False`)
        wall_channels (int, optional): with ``pairwise``, how many leading conditions are wall
            distances. (default: :obj:`0`)

    With ``pairwise``, ``forward`` may also take a ``frame`` ``[D + 1, H]``: the D directions in
    which a uniform change of every particle's velocity (a Galilean boost) moves the half latent,
    and the latent's origin (the encoder's bias). Each pair term is then read in its receiver's
    rest frame, both ends shifted by the receiver's own component along those directions
    (:func:`rest_frame_projection`, folded into the node terms: :meth:`first_layer`), so it
    depends on relative motion only: if every latent moves by the same boost, no pair term
    changes. The wall term keeps the absolute latent (walls are at rest).

    Shapes:
        - **input:** half latent :math:`(|\mathcal{V}|, H)`, edge indices :math:`(2, |\mathcal{E}|)`,
          edge latents :math:`(|\mathcal{E}|, H)`, node conditions :math:`(|\mathcal{V}|, C_{cond})`
        - **output:** :math:`(|\mathcal{V}|, H)`, the increment added to the other half
    """

    def __init__(self, channels: int, condition_channels: int, hidden_channels: int | None = None,
                 hidden_layers: int = 2, zero_init: bool = True, node_norm: bool = True, pairwise: bool = False,
                 wall_channels: int = 0):
        super().__init__(aggr="sum")
        if pairwise and not 0 < wall_channels <= condition_channels:
            raise ValueError(f"pairwise couplings read wall distances: wall_channels must be in 1..{condition_channels}")
        self.channels = channels
        self.zero_init = zero_init
        self.pairwise, self.wall_channels = pairwise, wall_channels
        self.edge_mlp = mlp(3 * channels, hidden_channels or channels, channels, hidden_layers)
        if pairwise:  # a bias would cancel in m_ij - m_ji
            self.edge_mlp[-1] = nn.LayerNorm(channels, bias=False)
        # pairwise: the wall term reads the particle's own half latent and its conditions only
        node_in = (1 if pairwise else 2) * channels + condition_channels
        self.node_mlp = mlp(node_in, hidden_channels or channels, channels, hidden_layers, layer_norm=node_norm)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        super().reset_parameters()
        for module in self.modules():
            if isinstance(module, (nn.Linear, nn.LayerNorm)):
                module.reset_parameters()
        if self.zero_init:  # the output's last affine map: the LayerNorm's, or the output layer
            last = self.node_mlp[-1] if isinstance(self.node_mlp[-1], nn.LayerNorm) else last_linear(self.node_mlp)
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
            if self.pairwise:  # the pair terms start at zero as well
                nn.init.zeros_(self.edge_mlp[-1].weight)

    def forward(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor, condition: Tensor,
                frame: Tensor | None = None) -> Tensor:
        """``frame [D + 1, H]``: with ``pairwise``, read the pair terms in their receivers' rest frames."""
        if frame is not None and not self.pairwise:
            raise ValueError("a rest frame applies to pairwise couplings only")
        first = self.edge_mlp[0]
        edge_weight, node_weight, node_bias = memoised(
            self, "first_layer", lambda: self.first_layer(frame), first.weight, first.bias, frame)
        receiver, sender = F.linear(x, node_weight, node_bias).chunk(2, dim=1)  # [N, H_hidden] each
        message = self.edge_updater(edge_index, receiver=receiver, sender=sender, edge_attr=edge_attr,
                                    edge_weight=edge_weight)  # [E, H]
        size = (x.size(0), x.size(0))
        aggregated = self.propagate(edge_index, message=message, size=size)  # [N, H]: what i receives
        if self.pairwise:
            # sum_j (m_ij - m_ji): the graph holds both directions, so m_ji is what i sends along i -> j
            aggregated = aggregated - self.propagate(edge_index.flip(0), message=message, size=size)
            near = wall_gate(condition[:, : self.wall_channels])  # [N, 1]: 1 at a wall, 0 from R on
            return aggregated + near * self.node_mlp(torch.cat([x, condition], dim=-1))
        return self.node_mlp(torch.cat([x, condition, aggregated], dim=-1))

    def first_layer(self, frame: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        r""":math:`f^e`'s first layer as :func:`~rgns.nn.mlp.split_first_layer` gives it; with a
        rest ``frame``, the receiver's shift folded into the node terms: :math:`W_r \mathbf{h}_i + b`
        becomes :math:`W_r \mathbf{h}_i + b - (W_r + W_s) P (\mathbf{h}_i - \mathbf{o})`
        (:func:`rest_frame_projection`): the sender's term, read at :math:`\mathbf{h}_j - s_i`,
        gives up its share of the receiver's shift :math:`s_i` to it. Computed once per weight
        in rollouts (:func:`~rgns.nn.mlp.memoised`)."""
        edge_weight, node_weight, node_bias = split_first_layer(self.edge_mlp[0], self.channels)
        if frame is None:
            return edge_weight, node_weight, node_bias
        projection, origin = rest_frame_projection(frame)  # [H, H], [H]
        own, other = node_weight.chunk(2)  # [H_hidden, H]: receiver, sender
        shift = (own + other) @ projection  # [H_hidden, H]
        receiver_bias, sender_bias = node_bias.chunk(2)
        return (edge_weight, torch.cat([own - shift, other]),
                torch.cat([receiver_bias + shift @ origin, sender_bias]))

    def edge_update(self, receiver_i: Tensor, sender_j: Tensor, edge_attr: Tensor, edge_weight: Tensor) -> Tensor:
        return self.edge_mlp[1:](gathered_linear(receiver_i, sender_j, edge_attr, edge_weight))

    def message(self, message: Tensor) -> Tensor:
        return message


def rest_frame_projection(frame: Tensor) -> tuple[Tensor, Tensor]:
    """The orthogonal projection ``P [H, H]`` onto the span of the boost directions of ``frame``
    (rows ``U [D, H]``, then the origin ``b [H]``), and the origin. A latent moved by a boost,
    ``x + a U``, has ``(x - b) P`` moved by ``a U``: subtracted from both ends of a pair, through
    a linear layer's receiver and sender weights, it cancels the boost in every pair.

    Shapes: frame ``[D + 1, H]``  ->  ``[H, H]``, ``[H]``"""
    directions, origin = frame[:-1], frame[-1]
    return directions.T @ torch.linalg.solve(directions @ directions.T, directions), origin


class ReversibleBlock(GroupAddRev):
    r"""A two-group :class:`torch_geometric.nn.GroupAddRev` whose memory-saving backward
    reconstructs each half and recomputes the function that produced it in one pass.

    GroupAddRev's own backward (``InvertibleFunction``) first runs the whole inverse to recover
    the input, then the whole forward again to rebuild the graph it differentiates: every
    coupling function is evaluated three times per training step (forward, inverse,
    recomputation). Here the backward walks the couplings in reverse order and evaluates each
    one once, with gradients enabled: its output both restores the half it was added to
    (Gomez et al. 2017, RevNet) and is differentiated. The forward and inverse maps are
    GroupAddRev's ``_forward`` and ``_inverse``; the input is freed in the forward pass and
    restored in the backward pass, as with GroupAddRev.

    Arguments are shared out as GroupAddRev does: tensors as wide as the latent are split in
    halves (the first to f, the second to g), anything else goes whole to both.
    """

    def __init__(self, convs: nn.ModuleList):
        super().__init__(convs)
        if self.num_groups != 2:
            raise ValueError(f"ReversibleBlock couples two halves, got {self.num_groups} groups")

    def _fn_apply(self, args, fn, fn_inverse):
        if self.disable:
            return fn(*args)
        parameters = tuple(p for p in self.parameters() if p.requires_grad)
        return _FusedReversible.apply(self, fn == self._inverse, len(args), *args, *parameters)


class _FusedReversible(torch.autograd.Function):
    """Autograd of :class:`ReversibleBlock`: frees the input, keeps the output, and in the backward
    pass rebuilds the input coupling by coupling while differentiating each coupling once."""

    @staticmethod
    def forward(ctx, block: ReversibleBlock, inverse: bool, num_args: int, *tensors):
        args = tensors[:num_args]
        with torch.no_grad():
            detached = [a.detach() if isinstance(a, Tensor) else a for a in args]
            output = (block._inverse if inverse else block._forward)(*detached)
        # free the input (an intermediate latent of the stack); the backward pass restores it
        args[0].untyped_storage().resize_(0)
        ctx.block, ctx.inverse, ctx.args, ctx.output = block, inverse, args, output
        ctx.needs = [isinstance(a, Tensor) and a.requires_grad for a in args]
        return output

    @staticmethod
    def backward(ctx, grad_output: Tensor):
        block, args, output = ctx.block, ctx.args, ctx.output
        if output.untyped_storage().size() == 0:
            raise RuntimeError("ReversibleBlock: its output was freed before its backward pass "
                               "(a second backward through a memory-saving block is not supported)")
        channels = output.size(block.split_dim)
        halves = list(torch.chunk(output, 2, dim=block.split_dim))  # walked back to the input
        grads = list(torch.chunk(grad_output, 2, dim=block.split_dim))
        extra, needs = args[1:], ctx.needs[1:]
        chunked = [block._chunk(a, channels) for a in extra]  # GroupAddRev's own sharing-out
        split = [chunks[0] is not a for chunks, a in zip(chunked, extra)]  # halves, or whole to both
        # each group's share of the extra arguments as leaves of its own, so its gradients are its own
        leaves = [[chunks[group].detach().requires_grad_(need) if isinstance(chunks[group], Tensor) else chunks[group]
                   for chunks, need in zip(chunked, needs)]
                  for group in range(2)]
        wanted = [i for i, need in enumerate(needs) if need]
        leaf_grads = [[None] * len(extra) for _ in range(2)]
        param_grads = [[] for _ in range(2)]
        params = [[p for p in conv.parameters() if p.requires_grad] for conv in block.convs]
        # the couplings in the order the pass applied them: (target half, source half, group, sign)
        steps = [(1, 0, 1, -1.0), (0, 1, 0, -1.0)] if ctx.inverse else [(0, 1, 0, 1.0), (1, 0, 1, 1.0)]
        for target, source, group, sign in reversed(steps):
            with torch.enable_grad():
                source_leaf = halves[source].detach().requires_grad_()
                out = block.convs[group](source_leaf, *leaves[group])
            with torch.no_grad():
                halves[target] = halves[target] - sign * out  # the half before this coupling
            got = torch.autograd.grad(out, [source_leaf] + [leaves[group][i] for i in wanted] + params[group],
                                      grad_outputs=sign * grads[target], allow_unused=True)
            grads[source] = grads[source] + got[0]
            for i, grad in zip(wanted, got[1 : 1 + len(wanted)]):
                leaf_grads[group][i] = grad
            param_grads[group] = got[1 + len(wanted):]
        with torch.no_grad():
            args[0].set_(torch.cat(halves, dim=block.split_dim))  # the previous block reads it in its backward
            output.untyped_storage().resize_(0)  # done with it
        arg_grads = [torch.cat(grads, dim=block.split_dim)]
        for index, (is_split, need) in enumerate(zip(split, needs)):
            if not need:
                arg_grads.append(None)
                continue
            parts = [_zero_if_none(leaf_grads[g][index], leaves[g][index]) for g in range(2)]
            if is_split:
                arg_grads.append(torch.cat(parts, dim=block.split_dim))
            else:
                arg_grads.append(parts[0] + parts[1])
        flat_params = [_zero_if_none(g, p) for group in range(2) for g, p in zip(param_grads[group], params[group])]
        return (None, None, None, *arg_grads, *flat_params)


def _zero_if_none(grad: Tensor | None, like: Tensor) -> Tensor:
    return torch.zeros_like(like) if grad is None else grad


class RRMP(nn.Module):
    r"""Residual Reversible Message Passing: ``layers`` two-group
    :class:`torch_geometric.nn.GroupAddRev` blocks (:class:`ReversibleBlock`) over
    :class:`Coupling` functions.

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
        memory_saving (bool, optional): memory-saving backward when gradients are enabled.
            (default: :obj:`True`)
        zero_init (bool, optional): start every block as the identity. (default: :obj:`True`)
        node_norm (bool, optional): end each coupling in a LayerNorm (see :class:`Coupling`).
            (default: :obj:`True`)
        pairwise (bool, optional): antisymmetrised pair terms plus a wall term in every coupling
            (see :class:`Coupling`). (default: :obj:`False`)
        wall_channels (int, optional): the leading conditions that are wall distances, for
            ``pairwise``. (default: :obj:`0`)

    Shapes:
        - **input:** node latents :math:`(|\mathcal{V}|, C)`, edge indices :math:`(2, |\mathcal{E}|)`,
          edge latents :math:`(|\mathcal{E}|, C)`, node conditions :math:`(|\mathcal{V}|, C_{cond})`
        - **output:** node latents :math:`(|\mathcal{V}|, C)`
    """

    def __init__(self, channels: int, layers: int, condition_channels: int, hidden_channels: int | None = None,
                 hidden_layers: int = 2, edges: str = "fixed", memory_saving: bool = True, zero_init: bool = True,
                 node_norm: bool = True, pairwise: bool = False, wall_channels: int = 0):
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
        self.memory_saving, self.pairwise = memory_saving, pairwise
        self.blocks = nn.ModuleList(
            ReversibleBlock(nn.ModuleList([
                Coupling(half, condition_channels, hidden_channels, hidden_layers, zero_init, node_norm, pairwise,
                         wall_channels)  # f, then g
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

    def _shared(self, x: Tensor, condition: Tensor, frame: Tensor | None) -> tuple[Tensor, ...]:
        """What every coupling reads besides its edge latent: the node conditions, and with
        ``pairwise`` the rest frame, if any."""
        if frame is None:
            return (condition,)
        if not self.pairwise:
            raise ValueError("a rest frame applies to pairwise couplings only")
        if frame.size(-1) != x.size(-1):
            raise ValueError(f"the rest frame spans {frame.size(-1)} latent channels, the latent {x.size(-1)}")
        # GroupAddRev gives the first half of a split argument to f, which reads the second half
        # of the latent, and the second to g, which reads the first: the frame's halves swapped
        first, second = frame.chunk(2, dim=-1)
        return condition, torch.cat([second, first], dim=-1)

    def forward(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor, condition: Tensor,
                frame: Tensor | None = None) -> Tensor:
        """``frame [D + 1, C]``: with ``pairwise``, pair terms read in their receivers' rest
        frames (:class:`Coupling`)."""
        self._set_memory_saving()
        shared = self._shared(x, condition, frame)
        for block, edge_latent in zip(self.blocks, self.edge_latents(edge_attr)):
            x = block(x, edge_index, edge_latent, *shared)
        return x

    def inverse(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor, condition: Tensor,
                frame: Tensor | None = None) -> Tensor:
        self._set_memory_saving()
        shared = self._shared(x, condition, frame)
        for block, edge_latent in zip(reversed(self.blocks), reversed(self.edge_latents(edge_attr))):
            x = block.inverse(x, edge_index, edge_latent, *shared)
        return x
