"""R-GNS: the Reversible Graph Network Simulator."""
from __future__ import annotations

import torch
from torch import Tensor, nn

from rgns.data.graph import edge_channels, edge_features, kernel_density
from rgns.models.base import Simulator, check_size, dataset_gravity
from rgns.nn import ILP, RRMP, MLPEncoderDecoder, mlp
from rgns.nn.mlp import memoised


class RGNS(Simulator):
    r"""One network for both directions of time: ILP encoder, RRMP processor, ILP decoder.

    Semi-symmetric input-output design: the node features are the normalised velocity history
    ``x = V [N, k D]``; the conditions (edge features of the graph of ``p^t``, type embedding,
    wall distances) are the same in both directions and never updated. Forward,
    ``V' = decode(RRMP(encode(V^t)))`` and only its newest slot is kept as ``v^{t+1}``; inverse,
    ``V = decode(RRMP^{-1}(encode(V^{t+1})))`` and only its oldest slot is kept as ``v^{t-k+1}``.
    At initialisation every coupling outputs zero, so the latent map is the identity and both
    directions start from constant-velocity extrapolation.

    R-GNS† (forward-only training) is this model trained with the forward loss alone.

    Args:
        metadata, history, noise_std, embedding, hard_walls: see :class:`~rgns.models.base.Simulator`.
        latent (int, optional): latent width, split in two halves by RRMP. (default: :obj:`128`)
        layers (int, optional): reversible blocks. (default: :obj:`10`)
        hidden (int, optional): MLP hidden width in the couplings. (default: ``latent // 2``)
        hidden_layers (int, optional): hidden layers per MLP. (default: :obj:`2`)
        encoder (str, optional): ``"ilp"`` (the paper's) or ``"mlp"`` (ablation). (default: ``"ilp"``)
        edges (str, optional): ``"fixed"`` (the paper's) or ``"updated"`` per layer from the
            conditions only (ablation). (default: ``"fixed"``)
        memory_saving (bool, optional): GroupAddRev's memory-saving backward in training.
            (default: :obj:`True`)
        zero_init (bool, optional): start at the identity latent map. (default: :obj:`True`)
        node_norm (bool, optional): end each coupling in a LayerNorm, which bounds the change of
            velocity per step (:class:`~rgns.nn.reversible.Coupling`); ``False`` drops it.
            (default: :obj:`True`)
        basis (str, optional): the node features the ILP reads, ``"velocity"`` (normalised
            velocities) or ``"differences"`` (see :meth:`to_basis`). (default: ``"velocity"``)
        known_gravity (bool, optional): a fixed shift by gravity ``g`` per frame
            (:func:`~rgns.models.base.dataset_gravity`) on the later history's side of the map:
            forward ``V^{t+1} = decode(RRMP(encode(V^t))) + g``, inverse
            ``V^t = decode(RRMP^{-1}(encode(V^{t+1} - g)))``, still exact inverses of each other.
            The identity latent map is then ballistic motion in both directions of time instead
            of constant velocity. (default: :obj:`False`)
        edge_velocity (bool, optional): the edge conditions also read the relative velocity
            ``v^t_j - v^t_i`` over the velocity std and its component along the edge
            (:func:`~rgns.data.graph.edge_features`). ``v^t`` is known in both directions of the
            step t <-> t+1 (the newest slot of ``V^t``, the second newest of ``V^{t+1}``), so the
            conditions stay shared and the inverse exact. Needs ``history >= 2``.
            (default: :obj:`False`)
        couplings (str, optional): ``"node"`` (the paper's: each coupling's increment is an MLP
            of the particle's half latent, conditions and summed messages) or ``"pairwise"``: a
            sum of antisymmetrised pair terms plus a term that only particles within R of a wall
            receive (:class:`~rgns.nn.reversible.Coupling`). The ILP is affine, so away from the
            walls the velocities' sum over the particles changes by gravity alone, in both
            directions of time (momentum conserved, as in DMCF). ``known_gravity`` is implied:
            with pair terms that cancel, a body could not otherwise fall. Still exactly
            invertible: a coupling may be any function of the other half and the conditions.
            (default: ``"node"``)
        density_condition (bool, optional): the edge latent also reads the kernel density
            (:func:`~rgns.data.graph.kernel_density`, less the particle's own 1: 0 for a particle
            alone) of both ends in ``p^t``, through a linear map that
            starts at zero. Antisymmetrised pair terms cannot sum a particle's neighbours into a
            density, so without it a pairwise model's pressure can only be a pair force of the
            distance; with it a pair term can be SPH's (a function of both densities times the
            kernel's gradient). The density is a condition of ``p^t``, shared by both directions,
            so the inverse stays exact. A checkpoint without it warm-starts this model
            (:meth:`warm_start_optional`). (default: :obj:`False`)
        galilean (bool, optional): with ``couplings="pairwise"`` and the ILP encoder, every pair
            term is read in its receiver's rest frame (:class:`~rgns.nn.reversible.Coupling`,
            :meth:`boost_frame`), so that the forces between particles depend on their relative
            motion only: moving every particle's velocity history by the same ``u`` moves the
            predicted velocities by ``u`` and changes nothing else, away from the walls (whose
            term keeps the absolute velocity). Without it a pair term reads both ends' absolute
            velocities, and a drop in free fall, whose particles all move alike, feels internal
            forces that grow with its speed. Adds no parameters: a checkpoint without it
            warm-starts this model (the pair terms then read other inputs at first). The inverse
            stays exact: each coupling is still a function of the other half and the conditions.
            (default: :obj:`False`)
    """

    display_name = "R-GNS"
    bidirectional = True

    def __init__(self, metadata: dict, history: int = 5, noise_std: float = 6.7e-4, latent: int = 128,
                 layers: int = 10, hidden: int | None = None, hidden_layers: int = 2, encoder: str = "ilp",
                 edges: str = "fixed", memory_saving: bool = True, zero_init: bool = True, node_norm: bool = True,
                 embedding: int = 16, hard_walls: bool = False, basis: str = "velocity", known_gravity: bool = False,
                 edge_velocity: bool = False, couplings: str = "node", density_condition: bool = False,
                 galilean: bool = False):
        super().__init__(metadata, history, noise_std, embedding, hard_walls)
        check_size("model.latent", latent, 2, even=True)
        check_size("model.layers", layers)
        if couplings not in ("node", "pairwise"):
            raise ValueError(f"couplings must be 'node' or 'pairwise', got {couplings!r}")
        known_gravity = known_gravity or couplings == "pairwise"
        if edge_velocity and history < 2:
            raise ValueError("edge_velocity needs history >= 2: v^t must be in both directions' histories")
        self.edge_velocity = bool(edge_velocity)
        if basis not in ("velocity", "differences"):
            raise ValueError(f"basis must be 'velocity' or 'differences', got {basis!r}")
        self.basis = basis
        self.known_gravity = bool(known_gravity)
        shift = dataset_gravity(metadata) if known_gravity else torch.zeros(self.dim)
        self.register_buffer("gravity_shift", shift, persistent=False)  # [D], computed, not saved in checkpoints
        node_in = history * self.dim
        if encoder == "ilp":
            self.projection = ILP(node_in, latent)
        elif encoder == "mlp":
            self.projection = MLPEncoderDecoder(node_in, latent, hidden_layers)
        else:
            raise ValueError(f"encoder must be 'ilp' or 'mlp', got {encoder!r}")
        # edge latent: geometry of the edge and the conditions of both ends, encoded once per step
        self.edge_encoder = mlp(edge_channels(self.dim, self.edge_velocity) + 2 * self.condition_channels, latent, latent, hidden_layers)
        self.density_condition = bool(density_condition)
        if self.density_condition:  # [receiver's, sender's] density -> a shift of the edge latent, zero at first
            self.density_encoder = nn.Linear(2, latent, bias=False)
            nn.init.zeros_(self.density_encoder.weight)
        if galilean and (couplings != "pairwise" or encoder != "ilp"):
            raise ValueError("galilean needs couplings='pairwise' (pair terms to read in a rest frame) and "
                             "encoder='ilp' (a boost must move the latent along fixed directions)")
        self.galilean = bool(galilean)
        self.zero_init = bool(zero_init)
        self.processor = RRMP(latent, layers, self.condition_channels, hidden, hidden_layers, edges,
                              memory_saving, zero_init, node_norm, pairwise=couplings == "pairwise",
                              wall_channels=2 * self.dim)  # node_conditions: the wall distances first

    def compile_network(self, **options) -> None:
        """See :meth:`~rgns.models.base.Simulator.compile_network`. Not with the memory-saving
        backward: its autograd function frees and restores storage, which a compiled graph does
        not follow (compiled, it computes other velocities)."""
        if self.processor.memory_saving:
            raise ValueError("R-GNS compiles only without the memory-saving backward: set model.memory_saving=false "
                             "(at the main job's size plain autograd is also the faster one on a CPU)")
        super().compile_network(**options)

    def conditions(self, position: Tensor, particle_type: Tensor, edge_index: Tensor,
                   velocity: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The fixed conditions of a step: edge latents ``[E, C]`` and node conditions ``[N, 2D + embedding]``.
        ``velocity [N, D]``: ``v^t``, read with ``edge_velocity``."""
        condition = self.node_conditions(position, particle_type)  # [N, 2D + embedding]
        sender, receiver = edge_index
        geometry = edge_features(position, edge_index, self.radius, velocity if self.edge_velocity else None,
                                 self.vel_std_noisy)  # [E, D + 1 (+ D + 1)]
        edges = torch.cat([geometry, condition[receiver], condition[sender]], dim=-1)
        edge_latent = self.edge_encoder(edges)  # [E, C]
        if self.density_condition:
            density = kernel_density(position, edge_index, self.radius) - 1  # [N]: the neighbours' share
            edge_latent = edge_latent + self.density_encoder(torch.stack([density[receiver], density[sender]], dim=-1))
        return edge_latent, condition

    def boost_frame(self) -> Tensor | None:
        """With ``galilean``: ``[D + 1, C]``, the D directions in which the encoded latent moves
        when every velocity of the history moves by a unit along each axis (the ILP's image of
        the boost through :meth:`to_basis`, which is affine), and the encoder's bias; else ``None``."""
        if not self.galilean:
            return None
        return memoised(self, "boost_frame", self._boost_frame, self.projection.weight, self.projection.bias,
                        self.vel_mean, self.vel_std_noisy, self.acc_std_noisy)  # once per weight in rollouts

    def _boost_frame(self) -> Tensor:
        weight = self.projection.weight  # [C, k D]
        unit = torch.eye(self.dim, dtype=weight.dtype, device=weight.device)[:, None, :].expand(-1, self.history, -1)
        moved = self.to_basis(unit) - self.to_basis(torch.zeros_like(unit))  # [D, k, D]: the affine part cancels
        return torch.cat([nn.functional.linear(moved.flatten(1), weight), self.projection.bias[None]])  # [D + 1, C]

    def warm_start_optional(self) -> set[str]:
        """See :meth:`~rgns.models.base.Simulator.warm_start_optional`: the density condition's map."""
        return {"density_encoder.weight"} if self.density_condition else set()

    def warm_start_added(self, present: set[str]) -> set[str]:
        """See :meth:`~rgns.models.base.Simulator.warm_start_added`: with ``zero_init`` every
        reversible block starts as the identity, so the blocks (and their edge updates) past the
        checkpoint's ``processor.blocks`` may be added after them."""
        if not self.zero_init:
            return set()
        depth = len({name.split(".")[2] for name in present if name.startswith("processor.blocks.")})
        return {name for name in self.state_dict()
                if name.startswith(("processor.blocks.", "processor.edge_updates.")) and int(name.split(".")[2]) >= depth}

    def to_basis(self, velocity_history: Tensor) -> Tensor:
        """Physical ``V [N, k, D]`` -> the node features ``[N, k, D]`` the ILP reads.

        ``basis="velocity"``: each velocity normalised by the velocity statistics.
        ``basis="differences"``: a fixed invertible change of basis around the middle slot ``c``:
        ``v^c`` normalised by the velocity statistics, every other slot as its difference to the
        neighbour towards ``c`` (newer slots ``v^j - v^{j-1}``, older ``v^{j+1} - v^j``) over the
        acceleration std. The newest and the oldest velocity are then the middle one plus a sum
        of accelerations, so a coupling's increment to the end slots is in acceleration units in
        both directions of time (GNS's precision) instead of velocity units.
        """
        if self.basis == "velocity":
            return self.normalise_velocity(velocity_history)
        return self.to_differences(velocity_history, anchor=self.history // 2)

    def from_basis(self, x: Tensor) -> Tensor:
        """The inverse of :meth:`to_basis`: ``[N, k, D]`` -> physical ``V [N, k, D]``."""
        if self.basis == "velocity":
            return self.denormalise_velocity(x)
        return self.from_differences(x, anchor=self.history // 2)

    def encode(self, velocity_history: Tensor) -> Tensor:
        return self.projection.encode(self.to_basis(velocity_history).flatten(1))  # [N, k D] -> [N, C]

    def decode(self, latent: Tensor) -> Tensor:
        return self.from_basis(self.projection.decode(latent).unflatten(1, (self.history, self.dim)))  # [N, k, D]

    def forward_history(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                        edge_index: Tensor) -> Tensor:
        """The unmasked forward output: ``V^t [N, k, D] -> decode(RRMP(encode(V^t))) (+ g) [N, k, D]``."""
        latent, frame = self.encode(velocity_history), self.boost_frame()
        with self.low_precision():  # the conditions and the couplings' increments; the latent stays float32
            edge_attr, condition = self.conditions(position, particle_type, edge_index, velocity_history[:, -1])  # v^t
            latent = self.processor(latent, edge_index, edge_attr, condition, frame)
        return self.decode(latent) + self.gravity_shift

    def inverse_history(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                        edge_index: Tensor) -> Tensor:
        """The unmasked inverse output: ``V^{t+1} [N, k, D] -> decode(RRMP^{-1}(encode(V^{t+1} (- g)))) [N, k, D]``."""
        latent, frame = self.encode(velocity_history - self.gravity_shift), self.boost_frame()
        with self.low_precision():
            edge_attr, condition = self.conditions(position, particle_type, edge_index, velocity_history[:, -2])  # v^t
            latent = self.processor.inverse(latent, edge_index, edge_attr, condition, frame)
        return self.decode(latent)

    def both_velocities(self, position: Tensor, forward_history: Tensor, inverse_history: Tensor,
                        particle_type: Tensor, edge_index: Tensor, batch: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Both directions of a training step on one graph, sharing the conditions (the edge
        encoder runs once for the two; ``v^t`` is ``forward_history``'s newest slot and
        ``inverse_history``'s second newest)."""
        forward, inverse = self.encode(forward_history), self.encode(inverse_history - self.gravity_shift)
        frame = self.boost_frame()
        with self.low_precision():
            edge_attr, condition = self.conditions(position, particle_type, edge_index, forward_history[:, -1])
            forward = self.processor(forward, edge_index, edge_attr, condition, frame)
            inverse = self.processor.inverse(inverse, edge_index, edge_attr, condition, frame)
        return (self.decode(forward)[:, -1] + self.gravity_shift,  # newest slot
                self.decode(inverse)[:, 0])  # oldest slot

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        return self.forward_history(position, velocity_history, particle_type, edge_index)[:, -1]  # newest slot

    def oldest_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                        edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        return self.inverse_history(position, velocity_history, particle_type, edge_index)[:, 0]  # oldest slot
