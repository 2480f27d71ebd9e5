"""GNS: the Graph Network Simulator of Sanchez-Gonzalez et al. (2020), as in DeepMind's
``learning_to_simulate/learned_simulator.py``."""
from __future__ import annotations

import torch
from torch import Tensor, nn

from rgns.data.graph import edge_channels, edge_features, wall_distance, wall_gate
from rgns.models.base import Simulator, check_size, dataset_gravity
from rgns.nn import InteractionNetwork, mlp
from rgns.nn.mlp import gathered_linear, memoised, split_first_layer


class GNS(Simulator):
    """Encode-process-decode on the radius graph of ``p^t``; predicts the normalised acceleration.

    - encode: node MLP on ``[normalised V^t (k D), wall distances (2 D), type embedding]``,
      edge MLP on ``[(p_j - p_i) / R, |p_j - p_i| / R]``;
    - process: ``layers`` unshared :class:`~rgns.nn.InteractionNetwork` steps;
    - decode: MLP without LayerNorm to the normalised acceleration;
      ``v^{t+1} = v^t + a^{t+1}``.

    Args:
        metadata, history, noise_std, embedding, hard_walls: see :class:`~rgns.models.base.Simulator`.
        latent (int, optional): latent width. (default: :obj:`128`)
        layers (int, optional): message-passing steps. (default: :obj:`10`)
        hidden_layers (int, optional): hidden layers per MLP. (default: :obj:`2`)
        basis (str, optional): the velocity features the node encoder reads: ``"velocity"``
            (DeepMind's: the k normalised velocities) or ``"differences"`` (the newest velocity
            normalised and the k - 1 accelerations over their std:
            :meth:`~rgns.models.base.Simulator.to_differences`). (default: ``"velocity"``)
        known_gravity (bool, optional): the decoder predicts the acceleration beyond gravity
            (:func:`~rgns.models.base.dataset_gravity`), normalised, instead of the acceleration
            beyond the dataset's mean: a particle the network leaves alone falls freely.
            (default: :obj:`False`)
        edge_velocity (bool, optional): the edge encoder also reads the relative newest velocity
            ``(v_j - v_i)`` over the velocity std and its component along the edge
            (:func:`~rgns.data.graph.edge_features`), not only the displacement: how fast a pair
            closes in, which the processor otherwise has to work out from two node latents.
            (default: :obj:`False`)
        decoder (str, optional): ``"node"`` (GNS's: an MLP per particle) or ``"pairwise"``: an
            MLP ``psi`` per edge on ``[h_i, h_j, g_ij]`` (``g``: the edge features), antisymmetrised,
            ``m_ij = psi(h_i, h_j, g_ij) - psi(h_j, h_i, g_ji)``, summed over the neighbours, plus a
            per-particle term that only particles within R of a wall receive (weighted by
            ``1 - distance / R``). The pair terms cancel in the sum over the particles: away from
            the walls the network conserves momentum, as DMCF's antisymmetric convolution does.
            Its reference is gravity (``known_gravity`` implied): with pair terms that cancel, the
            dataset's mean acceleration (gravity less the floor's support, averaged) would leave
            every falling body falling too slowly. (default: ``"node"``)
        galilean (bool, optional): with ``decoder="pairwise"``, everything the pair terms read is
            relative motion: the node encoder reads the ``k - 1`` accelerations of the history over
            their std and not the velocities, the edges read the relative newest velocity
            (``edge_velocity`` implied), and only the wall term, which acts within R of a wall,
            also reads the absolute newest velocity over the velocity std. Moving every velocity
            of the history by the same ``u`` then moves the predicted velocity by ``u`` and
            changes nothing else, away from the walls: a drop in free fall feels no internal
            forces that grow with its speed. R-GNS's ``galilean`` does the same through its linear
            encoder. Changes the node encoder's and the wall term's inputs, so a checkpoint without
            it does not warm-start this model. (default: :obj:`False`)
    """

    display_name = "GNS"

    def __init__(self, metadata: dict, history: int = 5, noise_std: float = 6.7e-4, latent: int = 128,
                 layers: int = 10, hidden_layers: int = 2, embedding: int = 16, hard_walls: bool = False,
                 basis: str = "velocity", known_gravity: bool = False, edge_velocity: bool = False,
                 decoder: str = "node", galilean: bool = False):
        super().__init__(metadata, history, noise_std, embedding, hard_walls)
        check_size("model.latent", latent)
        check_size("model.layers", layers)
        if basis not in ("velocity", "differences"):
            raise ValueError(f"basis must be 'velocity' or 'differences', got {basis!r}")
        if decoder not in ("node", "pairwise"):
            raise ValueError(f"decoder must be 'node' or 'pairwise', got {decoder!r}")
        self.basis, self.pairwise = basis, decoder == "pairwise"
        if galilean and not self.pairwise:
            raise ValueError("galilean needs decoder='pairwise': with a node decoder every particle's output reads "
                             "its own absolute velocity, so there are no pair terms to read in a rest frame")
        self.galilean = bool(galilean)
        known_gravity = known_gravity or self.pairwise
        self.known_gravity = bool(known_gravity)
        self.edge_velocity = bool(edge_velocity) or self.galilean
        if self.known_gravity:  # what a zero output of the decoder stands for (computed, not saved in checkpoints)
            self.register_buffer("gravity_reference", dataset_gravity(metadata), persistent=False)  # [D]
        node_in = (history - self.galilean) * self.dim + self.condition_channels  # galilean: no velocity, k - 1 accelerations
        self.node_encoder = mlp(node_in, latent, latent, hidden_layers)
        self.edge_encoder = mlp(edge_channels(self.dim, self.edge_velocity), latent, latent, hidden_layers)
        self.processor = nn.ModuleList(InteractionNetwork(latent, hidden_layers) for _ in range(layers))
        if self.pairwise:
            edge_in = 2 * latent + edge_channels(self.dim, self.edge_velocity)
            self.decoder = mlp(edge_in, latent, self.dim, hidden_layers, layer_norm=False)  # psi, per edge
            self.decoder[-1] = nn.Linear(latent, self.dim, bias=False)  # a bias would cancel in psi_ij - psi_ji
            wall_in = latent + self.dim * self.galilean  # galilean: the wall term also reads v^t
            self.wall_decoder = mlp(wall_in, latent, self.dim, hidden_layers, layer_norm=False)
        else:
            self.decoder = mlp(latent, latent, self.dim, hidden_layers, layer_norm=False)

    def geometry(self, position: Tensor, velocity_history: Tensor, edge_index: Tensor) -> Tensor:
        """The edge features ``[E, D + 1 (+ D + 1)]`` of ``edge_index``: displacement (and relative velocity)."""
        newest = velocity_history[:, -1] if self.edge_velocity else None  # v^t
        return edge_features(position, edge_index, self.radius, newest, self.vel_std_noisy)

    def encode(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
               geometry: Tensor) -> tuple[Tensor, Tensor]:
        """Node and edge latents ``[N, C]``, ``[E, C]`` from the state and the edge features (:meth:`geometry`)."""
        if self.galilean:  # the accelerations alone: to_differences' slots before the newest velocity's
            velocities = self.to_differences(velocity_history, anchor=self.history - 1)[:, :-1].flatten(1)  # [N, (k-1) D]
        elif self.basis == "velocity":
            velocities = self.normalise_velocity(velocity_history).flatten(1)  # [N, k D]
        else:
            velocities = self.to_differences(velocity_history, anchor=self.history - 1).flatten(1)  # [N, k D]
        nodes = torch.cat([velocities, self.node_conditions(position, particle_type)], dim=-1)
        return self.node_encoder(nodes), self.edge_encoder(geometry)  # [N, C], [E, C]

    def process(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor) -> Tensor:
        for layer in self.processor:
            x, edge_attr = layer(x, edge_index, edge_attr)
        return x

    def decode(self, x: Tensor, position: Tensor | None = None, edge_index: Tensor | None = None,
               geometry: Tensor | None = None, velocity: Tensor | None = None) -> Tensor:
        """The physical acceleration ``[N, D]``; the pairwise decoder also reads the scene (the
        positions, the graph and its edge features) and, with ``galilean``, the wall term the
        newest velocity ``velocity [N, D]``."""
        reference = self.gravity_reference if self.known_gravity else self.acc_mean  # [D]
        if not self.pairwise:
            return self.decoder(x) * self.acc_std_noisy + reference
        sender, receiver = edge_index
        # psi's first layer on [h_i, h_j, g_ij], its node terms computed once per node
        first = self.decoder[0]
        geometry_weight, node_weight, node_bias = memoised(
            self, "decoder_first_layer", lambda: split_first_layer(first, geometry.size(1), edge_first=False),
            first.weight, first.bias)
        node_terms = nn.functional.linear(x, node_weight, node_bias).chunk(2, dim=1)  # receiver's, sender's
        hidden = gathered_linear(node_terms[0][receiver], node_terms[1][sender], geometry, geometry_weight)
        into = self.decoder[1:](hidden).to(position.dtype)  # [E, D]: psi(h_i, h_j, g_ij)
        # sum_j psi(h_i, h_j, g_ij) - psi(h_j, h_i, g_ji): the second is psi on the reverse edge (the
        # graph holds both directions of every pair), which i sends: received less sent, sums to zero
        received = torch.zeros_like(position).index_add_(0, receiver, into)  # [N, D]
        pairs = received - torch.zeros_like(position).index_add_(0, sender, into)  # sums to zero
        near = wall_gate(wall_distance(position, self.bounds, self.radius))  # [N, 1]: 1 at a wall, 0 from R on
        wall_in = torch.cat([x, self.normalise_velocity(velocity)], -1) if self.galilean else x
        return (pairs + near * self.wall_decoder(wall_in)) * self.acc_std_noisy + reference

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        geometry = self.geometry(position, velocity_history, edge_index)  # [E, D + 1 (+ D + 1)]
        with self.low_precision():
            x, edge_attr = self.encode(position, velocity_history, particle_type, geometry)
            x = self.process(x, edge_index, edge_attr)
            acceleration = self.decode(x, position, edge_index, geometry, velocity_history[:, -1])
        return velocity_history[:, -1] + acceleration.to(velocity_history.dtype)  # dt = 1
