"""The graph shared by both directions of a step t <-> t+1: the radius graph of ``p^t``.

Edges follow PyG's convention: ``edge_index[0]`` are senders j, ``edge_index[1]`` receivers i,
messages flow j -> i. Both directions of every pair are present, no self-loops, no cap on the
number of neighbours (distances in float64, as scipy computes them).
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree


def radius_pairs(position: np.ndarray | torch.Tensor, radius: float) -> torch.Tensor:
    """All pairs ``i < j`` closer than ``radius`` (at most ``radius``, as scipy counts), once each.

    Shapes:
        position: ``[N, D]``  ->  ``[2, P]`` (int64, on the CPU)
    """
    if isinstance(position, torch.Tensor):
        position = position.detach().cpu().numpy()
    pairs = cKDTree(np.asarray(position, dtype=np.float64)).query_pairs(radius, output_type="ndarray")
    return torch.from_numpy(pairs.astype(np.int64)).t()  # [2, P]


def radius_graph(position: np.ndarray | torch.Tensor, radius: float) -> torch.Tensor:
    """All pairs closer than ``radius``, in both directions.

    Shapes:
        position: ``[N, D]``  ->  edge_index: ``[2, E]`` (int64, on the CPU)
    """
    pairs = radius_pairs(position, radius)  # [2, E/2]
    return torch.cat([pairs, pairs.flip(0)], dim=1)


def batched_radius_pairs(position: torch.Tensor, radius: float, batch: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`radius_pairs` of several disjoint graphs stacked as in a PyG ``Batch``.

    Shapes:
        position: ``[N, D]``, batch: ``[N]`` (graph id per node, sorted)  ->  ``[2, P]`` (on the CPU)
    """
    return _per_graph(radius_pairs, position, radius, batch)


def batched_radius_graph(position: torch.Tensor, radius: float, batch: torch.Tensor | None = None) -> torch.Tensor:
    """Radius graph of several disjoint graphs stacked as in a PyG ``Batch``.

    Shapes:
        position: ``[N, D]``, batch: ``[N]`` (graph id per node, sorted)  ->  ``[2, E]`` on ``position.device``
    """
    return _per_graph(radius_graph, position, radius, batch).to(position.device)


def _per_graph(edges, position: torch.Tensor, radius: float, batch: torch.Tensor | None) -> torch.Tensor:
    """``edges(position, radius)`` of each graph of a batch, numbered as in the batch."""
    if batch is None:
        return edges(position, radius)
    counts = torch.bincount(batch).tolist()
    parts, offset = [], 0
    for chunk in torch.split(position, counts):
        parts.append(edges(chunk, radius) + offset)
        offset += len(chunk)
    return torch.cat(parts, dim=1)


class NeighbourList:
    """The radius graph of a moving set of particles, step after step, from a list of candidate
    pairs kept between steps (a Verlet list): the pairs within ``radius + skin`` of the positions
    it was built at. While no particle has moved more than ``skin / 2`` since then, every pair
    now within ``radius`` is among them (two ends moved less than ``skin`` apart), so filtering
    the candidates by the true distance gives exactly the edges of a fresh :func:`radius_graph`
    (distances in float64 and ``<= radius``, as scipy counts them; the edges in another order).
    A larger displacement, other particles or another batch rebuild the candidates.

    Call it with each step's positions (``batch`` as in :func:`batched_radius_graph`); it returns
    the radius graph ``[2, E]`` on the positions' device. :attr:`builds` counts the builds.

    Args:
        radius (float): the connectivity radius R.
        skin (float): the margin of the candidates beyond R, in position units; 0 builds a
            fresh radius graph every call.
    """

    def __init__(self, radius: float, skin: float):
        if skin < 0:
            raise ValueError(f"a neighbour list's skin must be >= 0, got {skin}")
        self.radius, self.skin = float(radius), float(skin)
        self.builds = 0
        self._built_at: torch.Tensor | None = None  # [N, D] float64, where the candidates were found
        self._batch: torch.Tensor | None = None
        self._candidates: torch.Tensor | None = None  # [2, P] pairs within radius + skin there

    def __call__(self, position: torch.Tensor, batch: torch.Tensor | None = None) -> torch.Tensor:
        if self.skin == 0:
            return batched_radius_graph(position, self.radius, batch)
        current = position.detach().to("cpu", torch.float64)  # [N, D]
        if self._stale(current, batch):
            self._candidates = batched_radius_pairs(current, self.radius + self.skin, batch)
            self._built_at, self._batch = current, None if batch is None else batch.clone()
            self.builds += 1
        first, second = self._candidates
        distance2 = (current[first] - current[second]).pow(2).sum(-1)  # [P], as scipy sums them
        pairs = self._candidates[:, distance2 <= self.radius * self.radius]  # [2, E/2]
        return torch.cat([pairs, pairs.flip(0)], dim=1).to(position.device)

    def _stale(self, current: torch.Tensor, batch: torch.Tensor | None) -> bool:
        if self._built_at is None or self._built_at.shape != current.shape:
            return True
        if (batch is None) != (self._batch is None):
            return True
        if batch is not None and not torch.equal(batch.cpu(), self._batch.cpu()):
            return True
        moved = (current - self._built_at).pow(2).sum(-1).max()  # the largest squared displacement
        return bool(4 * moved >= self.skin * self.skin)  # some particle moved skin / 2 or more


def edge_features(position: torch.Tensor, edge_index: torch.Tensor, radius: float,
                  velocity: torch.Tensor | None = None, velocity_scale: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Relative displacement of sender to receiver over R, and its norm; with ``velocity``, also
    the relative velocity ``(v_j - v_i) / velocity_scale`` and its component along the
    displacement (positive: the pair separates, negative: it closes in).

    Shapes:
        position: ``[N, D]``, edge_index: ``[2, E]``, velocity: ``[N, D]`` or None,
        velocity_scale: ``[D]`` or scalar  ->  ``[E, D + 1]`` (``[E, 2 D + 2]`` with velocity)
    """
    sender, receiver = edge_index
    displacement = (position[sender] - position[receiver]) / radius  # [E, D]
    distance = displacement.norm(dim=-1, keepdim=True)  # [E, 1]
    if velocity is None:
        return torch.cat([displacement, distance], dim=-1)
    relative = (velocity[sender] - velocity[receiver]) / velocity_scale  # [E, D]
    closing = (relative * displacement).sum(-1, keepdim=True) / distance.clamp_min(1e-6)  # [E, 1]
    return torch.cat([displacement, distance, relative, closing], dim=-1)


def kernel_density(position: torch.Tensor, edge_index: torch.Tensor, radius: float) -> torch.Tensor:
    """SPH-style number density of every particle: 1 for itself plus ``(1 - r^2/R^2)^3`` for each
    neighbour at distance ``r < R`` along ``edge_index`` (sender -> receiver; pairs at ``R`` or
    beyond add 0, so the density is smooth in the positions).

    Shapes: position ``[N, D]``, edge_index ``[2, E]``  ->  ``[N]``"""
    sender, receiver = edge_index
    q = ((position[sender] - position[receiver]).pow(2).sum(-1) / radius**2).clamp(max=1.0)
    return torch.ones(len(position), dtype=position.dtype, device=position.device).index_add(0, receiver, (1 - q).pow(3))


def edge_union(first: torch.Tensor, second: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """Every edge of ``first`` or ``second`` once, sorted by sender then receiver (what
    ``torch.cat([first, second], 1).unique(dim=1)`` gives, through one-dimensional keys: an order of
    magnitude faster on a CPU).

    Shapes:
        first: ``[2, E1]``, second: ``[2, E2]``  ->  ``[2, E]`` (int64)
    """
    both = torch.cat([first, second], dim=1)
    key = torch.unique(both[0] * num_nodes + both[1])  # [E]
    return torch.stack([key // num_nodes, key % num_nodes])


def reverse_edges(edge_index: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """For every edge j -> i the index of its reverse i -> j, in a graph that holds both
    directions of every pair (as :func:`radius_graph` builds it).

    Raises ``ValueError`` (outside a compiled graph) when some edge has no reverse.

    Shapes:
        edge_index: ``[2, E]``  ->  ``[E]`` (int64)
    """
    sender, receiver = edge_index
    key = sender * num_nodes + receiver  # [E]
    order = torch.argsort(key)
    wanted = receiver * num_nodes + sender  # the reverse edge's key
    found = order[torch.searchsorted(key[order], wanted).clamp(max=max(len(key) - 1, 0))]
    if not torch.compiler.is_compiling() and not torch.equal(key[found], wanted):
        raise ValueError("the graph lacks the reverse of some edge: pairwise terms need both directions of every pair")
    return found


def edge_channels(dim: int, velocity: bool = False) -> int:
    """Width of :func:`edge_features` in ``dim`` dimensions, with or without the velocity terms."""
    return 2 * dim + 2 if velocity else dim + 1


def wall_distance(position: torch.Tensor, bounds: torch.Tensor, radius: float) -> torch.Tensor:
    """Distance to the lower and upper box bounds over R, clipped to [-1, 1] as in GNS.

    Shapes:
        position: ``[N, D]``, bounds: ``[D, 2]``  ->  ``[N, 2 D]``
    """
    lower = position - bounds[:, 0]
    upper = bounds[:, 1] - position
    return torch.cat([lower, upper], dim=-1).div(radius).clamp(-1.0, 1.0)


def wall_gate(walls: torch.Tensor) -> torch.Tensor:
    """1 at a wall, falling linearly to 0 at R from the nearest one: the weight of the pairwise
    models' wall term, read from :func:`wall_distance`'s features.

    Shapes:
        walls: ``[N, 2 D]`` in [-1, 1]  ->  ``[N, 1]``
    """
    return (1 - walls.min(dim=-1, keepdim=True).values).clamp(0, 1)
