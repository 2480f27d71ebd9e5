"""Rollouts of a simulator against a ground-truth trajectory: forward, inverse, and
inverse-then-forward consistency. Kinematic particles take their known positions."""
from __future__ import annotations

import torch

from rgns.models import State


@torch.no_grad()
def forward_rollout(model, position: torch.Tensor, particle_type: torch.Tensor, start: int, steps: int) -> torch.Tensor:
    """Roll out ``steps`` frames after frame ``start`` (which needs k frames before it).

    Shapes:
        position: ``[T, N, D]`` ground truth  ->  ``[steps, N, D]`` predicted frames start+1 ...
    """
    k = model.history
    state = State.from_positions(position[start - k : start + 1], particle_type)
    return model.rollout(state, steps, kinematic_positions=position[start + 1 : start + 1 + steps])


@torch.no_grad()
def inverse_then_forward(model, position: torch.Tensor, particle_type: torch.Tensor, start: int, steps: int):
    """From the true state at frame ``start + steps``, infer ``steps`` frames back, then roll forward.

    Returns the inferred positions (frames start+steps-1 ... start, ``[steps, N, D]``) and the
    re-simulated positions (frames start+1 ... start+steps, ``[steps, N, D]``).
    """
    k, end = model.history, start + steps
    state = State.from_positions(position[end - k : end + 1], particle_type)
    inferred = []
    for frame in range(end - 1, start - 1, -1):
        # the oldest velocity predicted at frame f fixes frame f - k: kinematic particles go there
        state = model.inverse_step(state, kinematic_position=position[frame - k] if frame >= k else None)
        inferred.append(state.position)
    resimulated = model.rollout(state, steps, kinematic_positions=position[start + 1 : end + 1])
    return torch.stack(inferred), resimulated
