"""Rollouts of a simulator against a ground-truth trajectory: forward, inverse, and
inverse-then-forward consistency. Kinematic particles take their known positions.

A model trained on every k-th frame (``data.stride = k``) steps k frames at a time; its forward
rollout is scored at every frame like any other's, the frames between its steps filled in along
straight lines (:func:`fill_frames`)."""
from __future__ import annotations

import math

import torch

from rgns.data.contract import KINEMATIC
from rgns.models import State


def fill_frames(first: torch.Tensor, strided: torch.Tensor, stride: int) -> torch.Tensor:
    """The frames between strided ones, on the straight line from each to the next: from frame 0
    (``first``) and frames ``k, 2k, .., nk`` (``strided``), frames ``1 .. nk``, frame
    ``k (j - 1) + r`` being ``P_{j-1} + (r / k) (P_j - P_{j-1})`` (``P_j`` itself at ``r = k``).

    Shapes:
        first: ``[N, D]``; strided: ``[n, N, D]``  ->  ``[n k, N, D]``
    """
    if stride == 1:
        return strided
    before = torch.cat([first[None], strided[:-1]])  # [n, N, D]: P_0 .. P_{n-1}
    fraction = torch.arange(1, stride + 1, dtype=strided.dtype, device=strided.device) / stride  # [k]: r / k
    # [n, k, N, D]: P_{j-1} + (r/k) (P_j - P_{j-1}); r = k gives P_j exactly
    filled = before[:, None] + fraction[None, :, None, None] * (strided - before)[:, None]
    filled[:, -1] = strided
    return filled.flatten(0, 1)


@torch.no_grad()
def forward_rollout(model, position: torch.Tensor, particle_type: torch.Tensor, start: int, steps: int,
                    stride: int = 1) -> torch.Tensor:
    """Roll out ``steps`` frames after frame ``start`` (which needs k frames before it, ``stride``
    frames apart).

    With ``stride`` s > 1 (a model trained on every s-th frame) the state at ``start`` is built
    from frames ``start - s k, .., start - s, start``, the model takes ``ceil(steps / s)`` steps
    of s frames, kinematic particles take their true positions at frames ``start + s j`` (the
    last known frame past the end of the trajectory) and at every frame in between, and the
    moving particles' frames in between are filled in along straight lines (:func:`fill_frames`).

    Shapes:
        position: ``[T, N, D]`` ground truth  ->  ``[steps, N, D]`` predicted frames start+1 ...
    """
    k = model.history
    if stride == 1:
        state = State.from_positions(position[start - k : start + 1], particle_type)
        return model.rollout(state, steps, kinematic_positions=position[start + 1 : start + 1 + steps])
    if start < stride * k:
        raise ValueError(f"start={start}: a model trained at stride {stride} with history {k} needs frames "
                         f"{start} - {stride} x {k} .. {start} (start >= {stride * k})")
    n = math.ceil(steps / stride)
    state = State.from_positions(position[start - stride * k : start + 1 : stride], particle_type)
    last = len(position) - 1
    known = position[[min(start + stride * j, last) for j in range(1, n + 1)]]  # [n, N, D]
    predicted = fill_frames(position[start], model.rollout(state, n, kinematic_positions=known), stride)[:steps]
    kinematic = particle_type == KINEMATIC
    truth = position[start + 1 : start + 1 + steps]
    predicted[: len(truth), kinematic] = truth[:, kinematic]
    return predicted


@torch.no_grad()
def inverse_then_forward(model, position: torch.Tensor, particle_type: torch.Tensor, start: int, steps: int):
    """From the true state at frame ``start + steps``, infer ``steps`` frames back, then roll forward.

    Returns the inferred positions (frames start+steps-1 ... start, ``[steps, N, D]``) and the
    re-simulated positions (frames start+1 ... start+steps, ``[steps, N, D]``). An inverse that turns
    non-finite is NaN from there on, and so is its whole re-simulation (not a crash).
    """
    k, end = model.history, start + steps
    state = State.from_positions(position[end - k : end + 1], particle_type)
    # row i of the kinematic positions: frame end - 1 - i (the oldest velocity predicted at frame f
    # fixes frame f - k, where kinematic particles go: Simulator.inverse_rollout)
    inferred, state = model.inverse_rollout(state, steps, position[:end].flip(0), return_state=True)
    if not (bool(torch.isfinite(state.position).all()) and bool(torch.isfinite(state.velocity_history).all())):
        return inferred, torch.full_like(inferred, float("nan"))  # an inverse that turned non-finite: nothing to run
    resimulated = model.rollout(state, steps, kinematic_positions=position[start + 1 : end + 1])
    return inferred, resimulated


@torch.no_grad()
def strided_inverse_then_forward(model, position: torch.Tensor, particle_type: torch.Tensor, start: int, steps: int,
                                 stride: int):
    """:func:`inverse_then_forward` of a model trained on every ``stride``-th frame, on the frames
    ``start, start + stride, ..``: ``steps / stride`` inverse steps back from the true state at
    ``start + steps`` (built from frames ``stride`` apart), then as many forward; the frames in
    between filled in along straight lines (:func:`fill_frames`), kinematic particles at their
    true positions. ``steps`` must be a multiple of ``stride``.

    Returns the inferred positions (frames start+steps-1 ... start, ``[steps, N, D]``) and the
    re-simulated positions (frames start+1 ... start+steps, ``[steps, N, D]``).
    """
    if stride == 1:
        return inverse_then_forward(model, position, particle_type, start, steps)
    if steps % stride:
        raise ValueError(f"{steps} inverse steps are not a whole number of steps of {stride} frames")
    phase = position[start % stride :: stride]  # frame start + stride j is its start // stride + j
    inferred, resimulated = inverse_then_forward(model, phase, particle_type, start // stride, steps // stride)
    end = start + steps
    inferred = fill_frames(position[end], inferred, stride)
    resimulated = fill_frames(inferred[-1], resimulated, stride)
    kinematic = particle_type == KINEMATIC
    inferred[:, kinematic] = position[start : end].flip(0)[:, kinematic]
    resimulated[:, kinematic] = position[start + 1 : end + 1][:, kinematic]
    return inferred, resimulated
