"""Baselines that need no training, behind the :class:`~rgns.models.Simulator` interface so
that every evaluation task runs them like a trained model. Each names itself (``label``)."""
from __future__ import annotations

import torch
from torch import Tensor

from rgns.data.contract import KINEMATIC
from rgns.models.base import Simulator, dataset_gravity


class ConstantVelocity(Simulator):
    """Constant-velocity extrapolation in both directions of time.

    Forward, each particle keeps its newest velocity: ``v^{t+1} = v^t``. Backward, it keeps its
    oldest one: ``v^{t-k+1} = v^{t-k+2}``. No parameters, no graph needed (the base class still
    builds it, so its timings include the neighbour search like every other method's).
    """

    bidirectional = True
    label = "Const. velocity"
    collapse_factor = None  # its piles against the walls are the motion it models, never a collapse to stop

    def __init__(self, metadata: dict, history: int = 5):
        super().__init__(metadata, history)
        del self.type_embedding  # no learned conditions

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        return velocity_history[:, -1]  # [N, D]

    def oldest_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                        edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        return velocity_history[:, 0]  # [N, D]


class Ballistic(ConstantVelocity):
    """Free flight under gravity inside the box's walls and outside the obstacles, in both
    directions of time.

    Forward: ``v = v^t + g``; the new position ``p^t + v`` is kept out of the obstacles and clamped
    into ``bounds``, and the velocity returned is that position minus ``p^t`` (so
    ``p^{t+1} = p^t + v^{t+1}`` holds and the velocity component into a wall is zeroed): a particle
    resting on the floor stays at rest. Backward, the mirror image: from ``p^{t-k+1}`` and its
    velocity ``v^{t-k+2}``, ``v = v^{t-k+2} - g``, the earlier position ``p^{t-k+1} - v`` is kept out
    of the obstacles and clamped into the box, and ``v^{t-k+1}`` is ``p^{t-k+1}`` minus it.

    Obstacles are the kinematic particles (a scene's ramps): each chain of them, neighbours at most
    1.5 times their closest spacing apart, is read as segments of thickness ``obstacle_radius``
    around them (capsules; a lone kinematic particle is a ball). A moving particle never ends a step
    closer to a segment than ``obstacle_radius`` or than it was, whichever is smaller (so one that
    the data starts inside an obstacle's margin is not pushed out); one that would is put back on
    that distance along the segment's normal. Without kinematic particles this is the box alone.

    ``g`` is in position units per frame squared: ``metadata["gravity"]`` (m/s^2) times
    ``metadata["dt"]`` squared. Datasets converted from DeepMind's files carry no ``gravity``;
    there the dataset's mean acceleration ``acc_mean`` (already per frame squared) stands in for
    it: the mean over every particle and frame, so contacts with the walls make it somewhat
    smaller than gravity.
    """

    label = "Ballistic + walls"

    def __init__(self, metadata: dict, history: int = 5, obstacle_radius: float | None = None):
        super().__init__(metadata, history)
        self.register_buffer("gravity", dataset_gravity(metadata))  # [D], per frame^2
        self.obstacle_radius = dataset_obstacle_radius(metadata) if obstacle_radius is None else float(obstacle_radius)

    def walls(self, position: Tensor, velocity: Tensor, obstacles: Segments | None = None) -> Tensor:
        """The velocity that takes ``position`` to ``position + velocity`` kept out of ``obstacles``
        and clamped into the box: ``velocity`` itself where nothing is hit (exactly, not re-derived
        from float32 positions).  ``[N, D]``"""
        target = position + velocity
        moved = target if obstacles is None else obstacles.keep_out(position, target, self.obstacle_radius)
        inside = torch.minimum(torch.maximum(moved, self.bounds[:, 0]), self.bounds[:, 1])
        return torch.where(inside == target, velocity, inside - position)

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        velocity = velocity_history[:, -1] + self.gravity  # [N, D], dt = 1
        return self.walls(position, velocity, Segments.of(position, particle_type, batch))

    def oldest_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                        edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        # position is p^t and velocity_history V^{t+1}: the oldest known frame is p^{t-k+1}
        oldest = position - velocity_history[:, :-1].sum(dim=1)  # [N, D]
        velocity = velocity_history[:, 0] - self.gravity
        obstacles = Segments.of(oldest, particle_type, batch)
        return -self.walls(oldest, -velocity, obstacles)  # back in time: p^{t-k} = p^{t-k+1} - v^{t-k+1}


def dataset_obstacle_radius(metadata: dict) -> float:
    """How close a moving particle's centre comes to an obstacle's chain of kinematic particles: the
    generating scene's ``ramp_radius`` (a ramp's half thickness) where the metadata records it, else
    half the connectivity radius (DeepMind's files record neither)."""
    params = (metadata.get("generator") or {}).get("params") or {}
    if params.get("ramp_radius") is not None:
        return float(params["ramp_radius"])
    return 0.5 * float(metadata["default_connectivity_radius"])


class Segments:
    """The obstacles as segments ``a -> b`` (``[L, D]`` each; ``graph [L]``: the batch entry of each),
    for the particles of ``batch [N]`` (``None``: one graph)."""

    def __init__(self, a: Tensor, b: Tensor, graph: Tensor, batch: Tensor | None = None):
        self.a, self.b, self.graph, self.batch = a, b, graph, batch

    @classmethod
    def of(cls, position: Tensor, particle_type: Tensor, batch: Tensor | None = None) -> Segments | None:
        """The chains of kinematic particles in ``position [N, D]``: a segment between every two of
        one graph at most 1.5 times the nearer's closest spacing apart, and a point segment at each
        (its ends and lone particles as balls). ``None`` without kinematic particles."""
        kinematic = particle_type == KINEMATIC
        if not bool(kinematic.any()):
            return None
        points = position[kinematic]  # [M, D]
        graph = torch.zeros(len(points), dtype=torch.long, device=points.device) if batch is None else batch[kinematic]
        distance = torch.cdist(points, points)  # [M, M]
        apart = (graph[:, None] != graph[None, :]) | torch.eye(len(points), dtype=torch.bool, device=points.device)
        distance = distance.masked_fill(apart, float("inf"))
        closest = distance.min(dim=1).values  # [M]; inf for a lone particle
        linked = (distance <= 1.5 * torch.minimum(closest[:, None], closest[None, :])) & ~apart  # lone ones: inf <= inf
        linked = torch.triu(linked, diagonal=1)
        i, j = linked.nonzero(as_tuple=True)
        return cls(torch.cat([points[i], points]), torch.cat([points[j], points]), torch.cat([graph[i], graph]), batch)

    def nearest(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Each point's nearest point on the segments of its graph and its distance: ``[N, D]``, ``[N]``."""
        ab = self.b - self.a  # [L, D]
        t = ((x[:, None] - self.a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-20)  # [N, L]
        foot = self.a + t.clamp(0.0, 1.0)[..., None] * ab  # [N, L, D]
        distance = (x[:, None] - foot).norm(dim=-1)  # [N, L]
        graph = torch.zeros(len(x), dtype=torch.long, device=x.device) if self.batch is None else self.batch
        distance = distance.masked_fill(graph[:, None] != self.graph[None, :], float("inf"))
        distance, k = distance.min(dim=1)  # [N]
        return foot[torch.arange(len(x), device=x.device), k], distance

    def keep_out(self, start: Tensor, end: Tensor, radius: float) -> Tensor:
        """``end [N, D]``, with each point that comes closer to the segments than ``radius`` and than
        ``start`` was put back on the smaller of the two distances, along the normal from its
        nearest segment point (from ``start``'s side where ``end`` lies on the segment)."""
        foot, after = self.nearest(end)
        if not bool((after < radius).any()):  # nobody within reach: the usual step, one distance pass
            return end
        _, before = self.nearest(start)
        allowed = torch.minimum(before, torch.full_like(before, radius))  # [N]
        into = after < allowed
        normal = end - foot
        on_axis = after < 1e-9
        normal = torch.where(on_axis[:, None], start - foot, normal)
        normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-20)
        return torch.where(into[:, None], foot + allowed[:, None] * normal, end)
