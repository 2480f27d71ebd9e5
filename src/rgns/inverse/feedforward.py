"""Feed-forward inverse inference (R-GNS, Sep-GNS), timed, and stability where methods fail.

- :func:`feed_forward_inverse`: K ``inverse_step`` s from a target state, timed as the paper's
  "inference time" (the K inverse steps only, radius graphs included), as an
  :class:`~rgns.inverse.optimise.InverseResult` so it sits beside the optimisation baselines;
- :func:`forward_stability`, :func:`inverse_stability`: long rollouts (1,000 steps and more,
  past the end of the data) with :func:`rgns.evaluation.metrics.divergence_step` deciding when a
  rollout breaks (NaN, a particle ``margin`` outside the box, kinetic energy ``energy_factor`` x a
  true trajectory's); each returns "stable for n steps".
"""
from __future__ import annotations

import time

import torch
from torch import Tensor

from rgns.data.contract import KINEMATIC
from rgns.evaluation.metrics import divergence_step, reference_speed
from rgns.inverse.optimise import InverseResult
from rgns.models import Simulator, State


@torch.no_grad()
def feed_forward_inverse(model: Simulator, state: State, steps: int) -> tuple[InverseResult, Tensor]:
    """K inverse steps back from ``state`` (the target at frame K).

    Returns the result (initial position ``[N, D]``, velocity history ``[N, k, D]``, ``seconds`` of
    the K steps) and the inferred positions of frames K-1 .. 0 ``[K, N, D]``.
    """
    if not model.bidirectional:
        raise ValueError(f"{type(model).__name__} has no inverse")
    frames = []
    begin = time.perf_counter()
    for _ in range(steps):
        state = model.inverse_step(state)
        frames.append(state.position)
    seconds = time.perf_counter() - begin
    result = InverseResult(state.position, state.velocity_history, "feed_forward", f"{steps} inverse steps",
                           seconds, steps, float("nan"))
    inferred = torch.stack(frames) if frames else state.position[:0].unsqueeze(0)
    return result, inferred


def _stable(positions: Tensor, particle_type: Tensor, bounds: Tensor, margin: float, speed: float,
            energy_factor: float) -> dict:
    moving = positions[:, particle_type != KINEMATIC]
    broken = divergence_step(moving.cpu(), bounds.cpu(), margin, speed, energy_factor)
    steps = len(positions)
    return dict(steps=steps, stable_steps=steps if broken is None else broken, diverged=broken is not None,
                stable_beyond_tested=broken is None)


def _stability(model: Simulator, state: State, advance, particle_type: Tensor, speed: float, steps: int,
               margin_radii: float, energy_factor: float, chunk: int) -> dict:
    """Advance ``state`` ``steps`` times with ``advance(state, i)``, checking every ``chunk`` steps
    and stopping early once the rollout breaks."""
    margin = margin_radii * model.radius
    frames = []
    for i in range(steps):
        state = advance(state, i)
        frames.append(state.position)
        if (i + 1) % chunk == 0 or i + 1 == steps:
            row = _stable(torch.stack(frames), particle_type, model.bounds, margin, speed, energy_factor)
            if row["diverged"]:
                return dict(row, steps=steps, stable_beyond_tested=False)
    return row


@torch.no_grad()
def forward_stability(model: Simulator, position: Tensor, particle_type: Tensor, start: int, steps: int = 1000,
                      margin_radii: float = 2.0, energy_factor: float = 100.0, chunk: int = 100) -> dict:
    """A forward rollout of ``steps`` frames from the true state at ``start`` of a trajectory
    ``[T, N, D]`` (past its end: kinematic particles stay at their last known positions), stopped
    early once it breaks. Returns ``stable_steps`` (the first broken step, 0-based, or ``steps``)."""
    state = State.from_positions(position[start - model.history: start + 1], particle_type)

    def advance(state: State, i: int) -> State:
        frame = start + 1 + i
        return model.step(state, kinematic_position=position[frame] if frame < len(position) else None)

    return _stability(model, state, advance, particle_type, reference_speed(position, particle_type), steps,
                      margin_radii, energy_factor, chunk)


@torch.no_grad()
def inverse_stability(model: Simulator, position: Tensor, particle_type: Tensor, end: int, steps: int = 1000,
                      margin_radii: float = 2.0, energy_factor: float = 100.0, chunk: int = 100) -> dict:
    """An inverse rollout of ``steps`` frames back from the true state at ``end`` of a trajectory
    (past frame 0 kinematic particles stay where they are), stopped early once it breaks.
    Returns ``stable_steps`` as :func:`forward_stability`."""
    if not model.bidirectional:
        raise ValueError(f"{type(model).__name__} has no inverse")
    state = State.from_positions(position[end - model.history: end + 1], particle_type)
    return _stability(model, state, lambda state, i: model.inverse_step(state), particle_type,
                      reference_speed(position, particle_type), steps, margin_radii, energy_factor, chunk)
