"""Baselines that need no training, behind the :class:`~rgns.models.Simulator` interface so
that every evaluation task runs them like a trained model. Each names itself (``label``)."""
from __future__ import annotations

import torch
from torch import Tensor

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
    """Free flight under gravity inside the box's walls, in both directions of time.

    Forward: ``v = v^t + g``, the new position ``p^t + v`` is clamped into ``bounds``, and the
    velocity returned is the clamped position minus ``p^t`` (so ``p^{t+1} = p^t + v^{t+1}`` holds
    and the velocity component into a wall is zeroed): a particle resting on the floor stays at
    rest. Backward, the mirror image: from ``p^{t-k+1}`` and its velocity ``v^{t-k+2}``,
    ``v = v^{t-k+2} - g``, the earlier position ``p^{t-k+1} - v`` is clamped into the box, and
    ``v^{t-k+1}`` is ``p^{t-k+1}`` minus it.

    ``g`` is in position units per frame squared: ``metadata["gravity"]`` (m/s^2) times
    ``metadata["dt"]`` squared. Datasets converted from DeepMind's files carry no ``gravity``;
    there the dataset's mean acceleration ``acc_mean`` (already per frame squared) stands in for
    it: the mean over every particle and frame, so contacts with the walls make it somewhat
    smaller than gravity.
    """

    label = "Ballistic + walls"

    def __init__(self, metadata: dict, history: int = 5):
        super().__init__(metadata, history)
        self.register_buffer("gravity", dataset_gravity(metadata))  # [D], per frame^2

    def walls(self, position: Tensor, velocity: Tensor) -> Tensor:
        """The velocity that takes ``position`` to ``position + velocity`` clamped into the box:
        ``velocity`` itself where no wall is hit (exactly, not re-derived from float32 positions).  ``[N, D]``"""
        target = position + velocity
        inside = torch.minimum(torch.maximum(target, self.bounds[:, 0]), self.bounds[:, 1])
        return torch.where(inside == target, velocity, inside - position)

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        velocity = velocity_history[:, -1] + self.gravity  # [N, D], dt = 1
        return self.walls(position, velocity)

    def oldest_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                        edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        # position is p^t and velocity_history V^{t+1}: the oldest known frame is p^{t-k+1}
        oldest = position - velocity_history[:, :-1].sum(dim=1)  # [N, D]
        velocity = velocity_history[:, 0] - self.gravity
        return -self.walls(oldest, -velocity)  # back in time: p^{t-k} = p^{t-k+1} - v^{t-k+1}
