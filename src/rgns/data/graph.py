"""The graph shared by both directions of a step t <-> t+1: the radius graph of ``p^t``.

Edges follow PyG's convention: ``edge_index[0]`` are senders j, ``edge_index[1]`` receivers i,
messages flow j -> i. Both directions of every pair are present, no self-loops, no cap on the
number of neighbours (distances in float64, as scipy computes them).
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree


def radius_graph(position: np.ndarray | torch.Tensor, radius: float) -> torch.Tensor:
    """All pairs closer than ``radius``.

    Shapes:
        position: ``[N, D]``  ->  edge_index: ``[2, E]`` (int64, on the CPU)
    """
    if isinstance(position, torch.Tensor):
        position = position.detach().cpu().numpy()
    pairs = cKDTree(np.asarray(position, dtype=np.float64)).query_pairs(radius, output_type="ndarray")
    pairs = torch.from_numpy(pairs.astype(np.int64)).t()  # [2, E/2]
    return torch.cat([pairs, pairs.flip(0)], dim=1)


def batched_radius_graph(position: torch.Tensor, radius: float, batch: torch.Tensor | None = None) -> torch.Tensor:
    """Radius graph of several disjoint graphs stacked as in a PyG ``Batch``.

    Shapes:
        position: ``[N, D]``, batch: ``[N]`` (graph id per node, sorted)  ->  ``[2, E]`` on ``position.device``
    """
    if batch is None:
        return radius_graph(position, radius).to(position.device)
    counts = torch.bincount(batch).tolist()
    parts, offset = [], 0
    for chunk in torch.split(position, counts):
        parts.append(radius_graph(chunk, radius) + offset)
        offset += len(chunk)
    return torch.cat(parts, dim=1).to(position.device)


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
