"""Baselines that need no training, behind the :class:`~rgns.models.Simulator` interface so
that every evaluation task runs them like a trained model."""
from __future__ import annotations

from torch import Tensor

from rgns.models import Simulator


class ConstantVelocity(Simulator):
    """Constant-velocity extrapolation in both directions of time.

    Forward, each particle keeps its newest velocity: ``v^{t+1} = v^t``. Backward, it keeps its
    oldest one: ``v^{t-k+1} = v^{t-k+2}``. No parameters, no graph needed (the base class still
    builds it, so its timings include the neighbour search like every other method's).
    """

    bidirectional = True

    def __init__(self, metadata: dict, history: int = 5):
        super().__init__(metadata, history)
        del self.type_embedding  # no learned conditions

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        return velocity_history[:, -1]  # [N, D]

    def oldest_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                        edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        return velocity_history[:, 0]  # [N, D]
