"""Metrics on particle sets and rollouts.

- rollout MSE as GNS defines it: mean over steps x particles x dims of squared position error;
- OT: squared 2-Wasserstein distance between two particle sets with uniform mass (exact, POT);
- MMD: squared maximum mean discrepancy with Gaussian kernels at the scale of the
  connectivity radius;
- Chamfer distance (symmetric mean of squared nearest-neighbour distances);
- density ratio: mean neighbours within the radius of one particle set over another's;
- stability: the first step at which a rollout diverges (NaN, particles leaving the box, kinetic
  energy blowing up).
"""
from __future__ import annotations

import numpy as np
import ot
import torch

from rgns.data.contract import KINEMATIC
from rgns.data.stats import mean_neighbours
from rgns.training.losses import gaussian_mmd


def mse_per_step(predicted: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """``[T, N, D]`` x 2 -> ``[T]``."""
    return (predicted - truth).pow(2).flatten(1).mean(1)


def with_last(steps: list[int], last: int) -> list[int]:
    """``steps`` (ascending, each at most ``last``) with ``last`` appended unless it ends them:
    the steps a per-step report covers, the rollout's last always among them."""
    return steps if steps and steps[-1] == last else steps + [last]


def rms_norm(vectors: torch.Tensor) -> float:
    """Root-mean-square length of vectors ``[..., D]``: per-frame velocities give the rms speed,
    accelerations less their mean the rms internal acceleration."""
    return float(vectors.pow(2).sum(-1).mean().sqrt())


def reference_speed(position: torch.Tensor, particle_type: torch.Tensor) -> float:
    """RMS per-frame speed of the moving particles of a true trajectory ``[T, N, D]``."""
    return rms_norm(torch.diff(position[:, particle_type != KINEMATIC], dim=0))


def rollout_mse(predicted: torch.Tensor, truth: torch.Tensor) -> float:
    return float((predicted - truth).pow(2).mean())


def density_ratio(x: torch.Tensor, reference: torch.Tensor, radius: float) -> float | None:
    """Mean neighbours within ``radius`` in ``x`` over those in ``reference`` (``[M, D]`` each):
    1 when ``x`` keeps the reference's density, above 1 when it is compressed, below when it
    spreads thinner. ``None`` for non-finite positions or no neighbours in the reference."""
    if not bool(torch.isfinite(x).all()):
        return None
    before = mean_neighbours(reference.cpu().numpy(), radius)
    return mean_neighbours(x.cpu().numpy(), radius) / before if before > 0 else None


def optimal_transport(x: torch.Tensor, y: torch.Tensor) -> float:
    """Squared W2 between point sets ``[N, D]`` and ``[M, D]`` with uniform weights."""
    x, y = x.detach().double().cpu().numpy(), y.detach().double().cpu().numpy()
    cost = ot.dist(x, y, metric="sqeuclidean")
    return float(ot.emd2(np.full(len(x), 1 / len(x)), np.full(len(y), 1 / len(y)), cost, numItermax=1_000_000))


def mmd(x: torch.Tensor, y: torch.Tensor, scale: float) -> float:
    """Squared MMD between point sets, Gaussian kernels of widths scale x (0.5, 1, 2)."""
    return float(gaussian_mmd(x.double() / scale, y.double() / scale))


def chamfer(x: torch.Tensor, y: torch.Tensor) -> float:
    distance = torch.cdist(x.double(), y.double()).pow(2)
    return float(distance.min(1).values.mean() + distance.min(0).values.mean()) / 2


def divergence_step(
    positions: torch.Tensor,
    bounds: torch.Tensor,
    margin: float,
    reference_speed: float,
    energy_factor: float = 100.0,
) -> int | None:
    """First step (0-based) at which a rollout ``[T, N, D]`` is broken, or None if it never is.

    Broken means: a NaN/Inf, a particle more than ``margin`` outside ``bounds [D, 2]``, or a
    mean kinetic energy (per-frame speed squared) over ``energy_factor`` times that of
    ``reference_speed`` (a typical true speed per frame).
    """
    finite = torch.isfinite(positions).flatten(1).all(1)
    outside = ((positions < bounds[:, 0] - margin) | (positions > bounds[:, 1] + margin)).flatten(1).any(1)
    velocity = torch.diff(positions, dim=0, prepend=positions[:1])
    energy = velocity.pow(2).sum(-1).mean(-1)
    exploding = energy > energy_factor * reference_speed**2
    broken = (~finite) | outside | exploding
    hits = broken.nonzero()
    return int(hits[0]) if len(hits) else None
