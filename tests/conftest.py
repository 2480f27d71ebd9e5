"""Shared fixtures: tiny datasets written through the data contract."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from rgns.data.contract import KINEMATIC, SPLITS, WATER, write_metadata, write_split
from rgns.models import State

torch.set_num_threads(1)


def make_metadata(dim: int = 2, radius: float = 0.08, frames: int = 20) -> dict:
    return dict(
        bounds=[[0.1, 0.9]] * dim,
        sequence_length=frames - 1,
        default_connectivity_radius=radius,
        dim=dim,
        dt=0.0025,
        vel_mean=[0.0] * dim,
        vel_std=[1e-3] * dim,
        acc_mean=[0.0] * dim,
        acc_std=[1e-4] * dim,
    )


def random_trajectory(rng: np.random.Generator, frames: int = 20, particles: int = 60, dim: int = 2, kinematic: int = 6):
    """Brownian particles in the box; the last ``kinematic`` particles are type 3 and never move."""
    start = rng.uniform(0.2, 0.8, (1, particles, dim))
    steps = rng.normal(scale=1e-3, size=(frames, particles, dim))
    steps[:, particles - kinematic :] = 0.0
    position = (start + np.cumsum(steps, axis=0)).astype(np.float32)
    particle_type = np.full(particles, WATER, dtype=np.int64)
    particle_type[particles - kinematic :] = KINEMATIC
    return position, particle_type


def random_state(particles: int = 60, dim: int = 2, kinematic: int = 0, seed: int = 0, low: float = 0.15,
                 span: float = 0.7, history: int = 5) -> State:
    """A model input: particles uniform in ``[low, low + span]^D`` with small random velocities
    (``history`` of them); the last ``kinematic`` particles are type 3 and at rest."""
    generator = torch.Generator().manual_seed(seed)
    position = low + span * torch.rand(particles, dim, generator=generator)
    velocity = 2e-3 * torch.randn(particles, history, dim, generator=generator)
    particle_type = torch.full((particles,), WATER)
    particle_type[particles - kinematic:] = KINEMATIC
    velocity[particle_type == KINEMATIC] = 0.0
    return State(position, velocity, particle_type)


def perturb(module: torch.nn.Module, scale: float = 0.1, seed: int = 0) -> torch.nn.Module:
    """Every parameter moved off its initialisation by ``scale`` times a standard normal draw
    (R-GNS starts as the identity map); returns the module."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in module.parameters():
            parameter.add_(scale * torch.randn(parameter.shape, generator=generator))
    return module


@pytest.fixture
def tiny_dataset(tmp_path):
    """A 2D dataset folder: 3 train, 2 valid, 2 test trajectories of 20 frames, 60 particles."""
    rng = np.random.default_rng(0)
    for split, count in zip(SPLITS, (3, 2, 2)):
        write_split(tmp_path / f"{split}.h5", [random_trajectory(rng) for _ in range(count)])
    write_metadata(tmp_path, make_metadata())
    return tmp_path


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A 2/1/1-trajectory dataset of 30 frames, shared by a module's train.py runs."""
    root = tmp_path_factory.mktemp("data")
    rng = np.random.default_rng(0)
    for split, count in zip(SPLITS, (2, 1, 1)):
        write_split(root / f"{split}.h5", [random_trajectory(rng, frames=30) for _ in range(count)])
    write_metadata(root, make_metadata(frames=30))
    return root


def train_steps(module, batch, steps: int, lr: float) -> list[float]:
    """``steps`` Adam steps of a SimulatorModule on one batch; every step's gradient must be
    finite and reach every parameter. Returns the losses."""
    optimizer = torch.optim.Adam(module.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        optimizer.zero_grad()
        loss = module._losses(batch)["loss"]
        loss.backward()
        for name, parameter in module.named_parameters():
            assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name
        losses.append(loss.item())
        optimizer.step()
    return losses
