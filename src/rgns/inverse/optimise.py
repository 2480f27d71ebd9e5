"""Optimisation-based inverse inference: Adam on the initial state through a differentiable simulator.

Given a target state at frame K (positions, optionally the newest velocity), find an initial
state ``(p^0, V^0)`` such that K frames of a differentiable simulator reach it:

    minimise  L(p^0, V^0) = mean |p^K - p*|^2  +  w_v mean |v^K - v*|^2,   w_v = K^2 by default
    (p^K, v^K) = simulate(p^0, V^0, K)

The simulator is anything with ``simulate(position [N, D], velocity, steps) -> (position [N, D],
velocity [N, D])`` differentiable in torch (see :mod:`rgns.inverse.simulators`). Velocities are
per frame (position differences, dt = 1), as in the data contract; ``velocity`` is ``[N, D]`` for
the physical solvers and the velocity history ``[N, k, D]`` for a learned simulator. The default
velocity weight ``K^2`` measures a velocity error by the position error it makes over the horizon,
which keeps the two terms of the same size (with weight 1 the velocity term is ~1e-6 of the
position term in per-frame units and the problem is badly conditioned).

**The stopping rule** (:class:`StoppingRule`), the same for every method and target. After each
evaluation of the loss and its gradient, in this order:

1. *failed* -- the simulator raised (e.g. SPH's neighbour slots overflowed); the loss or the
   gradient is NaN/Inf; or the gradient norm (before clipping)
   exceeds ``max_grad_norm``; or, for ``patience`` consecutive iterations, the loss stayed above
   both ``divergence_factor`` times the best loss so far and the first iterate's loss (divergence:
   worse than where it started, not Adam's jitter near a minimum);
2. *converged* -- the loss is below ``abs_tol``; or the best loss improved by less than a
   fraction ``rel_tol`` over the last ``window`` iterations;
3. *iteration_cap* -- ``max_iterations`` evaluations were spent (or ``max_seconds`` of wall
   clock, when set) without 1 or 2.

The result always carries the best iterate seen (lowest loss) and its loss, never the last one,
and a ``status`` / ``reason`` that callers must read: a *failed* result's state is the best one
before the failure, reported as failed, not passed off as a solution.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import torch
from torch import Tensor


class DifferentiableSimulator(Protocol):
    """What the optimiser needs of a simulator."""

    def simulate(self, position: Tensor, velocity: Tensor, steps: int) -> tuple[Tensor, Tensor]:
        """``steps`` frames from ``(position [N, D], velocity)``: final position and newest velocity ``[N, D]``,
        differentiable with respect to both inputs."""
        ...


@dataclass
class StoppingRule:
    """When an optimisation stops (see the module docstring for the order of the checks).

    Args:
        max_iterations: loss-and-gradient evaluations at most.
        abs_tol: converged when the loss falls below this (position units squared).
        rel_tol, window: converged when the best loss improved by less than ``rel_tol`` (a
            fraction) over the last ``window`` iterations.
        divergence_factor, patience: failed when the loss stays above ``divergence_factor`` x
            the best loss and above the first loss for ``patience`` consecutive iterations.
        max_grad_norm: failed when the gradient norm before clipping exceeds this.
        max_seconds: a wall-clock cap (``None``: none); reached, it ends as ``iteration_cap``.
    """

    max_iterations: int = 200
    abs_tol: float = 1e-9
    rel_tol: float = 1e-3
    window: int = 10
    divergence_factor: float = 10.0
    patience: int = 3
    max_grad_norm: float = 1e6
    max_seconds: float | None = None


@dataclass
class InverseResult:
    """What an inverse solve returns: the initial state and how the solve went.

    ``status`` is ``"converged"``, ``"failed"`` or ``"iteration_cap"`` (feed-forward inference:
    ``"feed_forward"``); ``reason`` says why in words. ``loss`` is the best loss (that of the
    returned state); ``loss_history`` / ``grad_norm_history`` one value per iteration.
    """

    initial_position: Tensor  # [N, D]
    initial_velocity: Tensor  # [N, D] or [N, k, D]
    status: str
    reason: str
    seconds: float
    iterations: int
    loss: float
    loss_history: list[float] = field(default_factory=list)
    grad_norm_history: list[float] = field(default_factory=list)
    lr: float | None = None  # the positions' initial rate actually used

    @property
    def ok(self) -> bool:
        return self.status != "failed"

    def summary(self) -> dict:
        """Plain numbers for a JSON report (no tensors)."""
        finite = [v for v in self.loss_history if math.isfinite(v)]
        return dict(status=self.status, reason=self.reason, seconds=self.seconds, iterations=self.iterations,
                    loss=self.loss if math.isfinite(self.loss) else None,
                    initial_loss=finite[0] if finite else None, lr=self.lr)


def state_loss(position: Tensor, target_position: Tensor, velocity: Tensor | None = None,
               target_velocity: Tensor | None = None, velocity_weight: float = 1.0,
               mask: Tensor | None = None) -> Tensor:
    """Mean squared error of the positions (plus ``velocity_weight`` x that of the newest velocity when a
    target velocity is given), over the particles in ``mask [N]`` (all when ``None``)."""
    if mask is not None:
        position, target_position = position[mask], target_position[mask]
    loss = (position - target_position).pow(2).mean()
    if target_velocity is not None:
        if mask is not None:
            velocity, target_velocity = velocity[mask], target_velocity[mask]
        loss = loss + velocity_weight * (velocity - target_velocity).pow(2).mean()
    return loss


def make_scheduler(schedule: str | Callable | None, optimizer: torch.optim.Optimizer, iterations: int):
    """``None``/``"constant"``, ``"cosine"`` (to 1% of the rate at the cap), ``"exponential"`` (to 1% at
    the cap), or a callable ``optimizer -> scheduler`` (e.g. a Hydra ``_partial_``)."""
    if schedule is None or schedule == "constant":
        return None
    if callable(schedule):
        return schedule(optimizer)
    if schedule == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(iterations, 1),
                                                          eta_min=0.01 * optimizer.param_groups[0]["lr"])
    if schedule == "exponential":
        return torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=0.01 ** (1 / max(iterations, 1)))
    raise ValueError(f"schedule must be None, 'constant', 'cosine', 'exponential' or a callable, got {schedule!r}")


def optimise_initial_state(
    simulator: DifferentiableSimulator,
    target_position: Tensor,
    steps: int,
    init_position: Tensor | None = None,
    init_velocity: Tensor | None = None,
    target_velocity: Tensor | None = None,
    velocity_weight: float | None = None,
    lr: float | None = None,
    velocity_lr: float | None = None,
    schedule: str | Callable | None = "cosine",
    clip: float | None = None,
    rule: StoppingRule | None = None,
    mask: Tensor | None = None,
) -> InverseResult:
    """Optimise ``(p^0, V^0)`` with Adam so that ``steps`` frames of ``simulator`` reach the target.

    Args:
        simulator: see :class:`DifferentiableSimulator`.
        target_position: ``[N, D]`` at frame ``steps``; target_velocity: ``[N, D]`` newest velocity there (optional).
        init_position, init_velocity: the first guess (default: the target positions, and zero
            velocity of the shape ``simulator.velocity_shape`` if it has one, else ``[N, D]``).
        velocity_weight: weight of the velocity term of the loss (default ``steps ** 2``).
        lr: Adam's rate for the positions (position units per iteration; Adam's first steps move
            every coordinate by about this much). ``None``: a tenth of the first iterate's RMS
            position error, ``0.1 sqrt(L_0)``, so the step fits the error whatever the horizon.
        velocity_lr: for the velocities (default ``lr / steps``: a velocity error moves frame
            ``steps`` ``steps`` times as far).
        schedule: see :func:`make_scheduler`. clip: clip the gradient's total norm to this (None: no clipping).
        rule: the :class:`StoppingRule` (default: its defaults).
        mask: ``[N]`` bool, the particles in the loss (e.g. not kinematic); all when ``None``.

    Returns an :class:`InverseResult` with the best initial state found.
    """
    rule = rule or StoppingRule()
    velocity_weight = float(steps) ** 2 if velocity_weight is None else velocity_weight
    target_position = target_position.detach()
    target_velocity = None if target_velocity is None else target_velocity.detach()
    if init_position is None:
        init_position = target_position
    if init_velocity is None:
        shape = getattr(simulator, "velocity_shape", lambda n: (n, target_position.shape[-1]))(len(target_position))
        init_velocity = torch.zeros(shape, dtype=target_position.dtype, device=target_position.device)
    position = init_position.detach().clone().requires_grad_(True)
    velocity = init_velocity.detach().clone().requires_grad_(True)
    optimizer = scheduler = None  # built at the first update, once the first loss is known

    losses, grad_norms, best_history = [], [], []
    best = (math.inf, position.detach().clone(), velocity.detach().clone())
    status, reason, above = "iteration_cap", f"reached the cap of {rule.max_iterations} iterations", 0
    start = time.perf_counter()
    iteration = 0
    for iteration in range(1, rule.max_iterations + 1):
        try:
            final_position, final_velocity = simulator.simulate(position, velocity, steps)
        except (RuntimeError, FloatingPointError, ValueError) as error:  # e.g. SPH's neighbour slots overflowed
            status, reason = "failed", f"the simulator raised at iteration {iteration}: {error}"
            break
        loss = state_loss(final_position, target_position, final_velocity, target_velocity, velocity_weight, mask)
        value = float(loss.detach())
        losses.append(value)
        if not math.isfinite(value):
            grad_norms.append(math.nan)
            status, reason = "failed", f"loss is {value} at iteration {iteration}"
            break
        grads = torch.autograd.grad(loss, [position, velocity], allow_unused=True)  # not into a model's weights
        grads = [torch.zeros_like(p) if g is None else g for p, g in zip((position, velocity), grads)]
        position.grad, velocity.grad = grads
        grad_norm = float(torch.sqrt(sum(g.double().pow(2).sum() for g in grads)))
        grad_norms.append(grad_norm)
        if value < best[0]:  # this iterate's loss is known: keep it if it is the best
            best = (value, position.detach().clone(), velocity.detach().clone())
        best_history.append(best[0])
        if not math.isfinite(grad_norm):
            status, reason = "failed", f"gradient is non-finite at iteration {iteration}"
            break
        if grad_norm > rule.max_grad_norm:
            status, reason = "failed", (f"exploding gradient: norm {grad_norm:.3g} > {rule.max_grad_norm:.3g} "
                                        f"at iteration {iteration}")
            break
        above = above + 1 if value > max(rule.divergence_factor * best[0], losses[0]) else 0
        if above >= rule.patience:
            status, reason = "failed", (f"diverged: loss above the first ({losses[0]:.3g}) and "
                                        f"{rule.divergence_factor:g}x the best ({best[0]:.3g}) for {above} "
                                        f"iterations (now {value:.3g}) at iteration {iteration}")
            break
        if value < rule.abs_tol:
            status, reason = "converged", f"loss {value:.3g} < abs_tol {rule.abs_tol:g} at iteration {iteration}"
            break
        if len(best_history) > rule.window:
            before = best_history[-1 - rule.window]
            if before - best[0] <= rule.rel_tol * before:
                status, reason = "converged", (f"best loss improved by < {rule.rel_tol:g} (relative) over "
                                               f"{rule.window} iterations at iteration {iteration}")
                break
        if rule.max_seconds is not None and time.perf_counter() - start > rule.max_seconds:
            status, reason = "iteration_cap", f"reached the time cap of {rule.max_seconds:g} s at iteration {iteration}"
            break
        if iteration == rule.max_iterations:
            break  # no update after the last evaluation: its loss would be unknown
        if clip is not None:
            torch.nn.utils.clip_grad_norm_([position, velocity], clip)
        if optimizer is None:
            lr = lr if lr is not None else 0.1 * math.sqrt(max(value, 1e-30))
            optimizer = torch.optim.Adam([
                {"params": [position], "lr": lr},
                {"params": [velocity], "lr": velocity_lr if velocity_lr is not None else lr / max(steps, 1)}])
            scheduler = make_scheduler(schedule, optimizer, rule.max_iterations)
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
    seconds = time.perf_counter() - start
    iteration = len(losses)  # evaluations completed
    return InverseResult(best[1], best[2], status, reason, seconds, iteration, best[0], losses, grad_norms,
                         lr if optimizer is not None else None)
