"""Streamed velocity/acceleration statistics against numpy on everything at once."""
from __future__ import annotations

import numpy as np
import pytest

from rgns.data.contract import KINEMATIC, RIGID, SAND, WATER, open_split, read_metadata
from rgns.data.generate import generate_dataset, scene_config
from rgns.data.stats import RunningMoments, compute_statistics, dataset_regime, regime


def random_trajectories(rng: np.random.Generator, dim: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Trajectories of different lengths and sizes, with mixed types and wildly moving kinematic
    particles (velocities ~1e3 times the fluid's), so that counting them would change every statistic."""
    trajectories = []
    for frames, particles in [(12, 30), (2, 7), (25, 19), (9, 44)]:
        particle_type = rng.choice([WATER, SAND, RIGID, KINEMATIC], particles).astype(np.int64)
        particle_type[:2] = [WATER, KINEMATIC]
        steps = rng.normal(loc=2e-4, scale=1e-3, size=(frames, particles, dim))
        steps[:, particle_type == KINEMATIC] *= 1e3
        position = (0.5 + np.cumsum(steps, axis=0)).astype(np.float32)
        trajectories.append((position, particle_type))
    return trajectories


def numpy_statistics(trajectories) -> dict[str, np.ndarray]:
    """Every velocity and acceleration of every moving particle, concatenated, then mean and std."""
    velocities, accelerations = [], []
    for position, particle_type in trajectories:
        moving = position[:, particle_type != KINEMATIC].astype(np.float64)
        velocity = np.diff(moving, axis=0)  # dt = 1: per frame
        velocities.append(velocity.reshape(-1, position.shape[-1]))
        accelerations.append(np.diff(velocity, axis=0).reshape(-1, position.shape[-1]))
    velocities, accelerations = np.concatenate(velocities), np.concatenate(accelerations)
    return {
        "vel_mean": velocities.mean(0),
        "vel_std": velocities.std(0),
        "acc_mean": accelerations.mean(0),
        "acc_std": accelerations.std(0),
    }


@pytest.mark.parametrize("dim", [2, 3])
def test_streamed_statistics_equal_numpy(dim):
    trajectories = random_trajectories(np.random.default_rng(dim), dim)
    expected = numpy_statistics(trajectories)
    streamed = compute_statistics(iter(trajectories))  # a one-pass iterator, as from a split file
    assert set(streamed) == set(expected)
    for key, value in streamed.items():
        assert isinstance(value, list) and len(value) == dim
        np.testing.assert_allclose(value, expected[key], rtol=1e-10, atol=0, err_msg=key)


def test_kinematic_particles_are_left_out():
    trajectories = random_trajectories(np.random.default_rng(0), 2)
    with_kinematic = compute_statistics(trajectories)
    as_water = compute_statistics([(p, np.where(t == KINEMATIC, WATER, t)) for p, t in trajectories])
    # the kinematic particles move ~1e3 times faster: counting them would blow the std up
    assert np.all(np.array(as_water["vel_std"]) > 10 * np.array(with_kinematic["vel_std"]))
    assert np.all(np.array(with_kinematic["vel_std"]) < 2e-3)


def test_order_of_trajectories_does_not_matter():
    trajectories = random_trajectories(np.random.default_rng(5), 3)
    forward, backward = compute_statistics(trajectories), compute_statistics(trajectories[::-1])
    for key in forward:
        np.testing.assert_allclose(forward[key], backward[key], rtol=1e-10, atol=0, err_msg=key)


def test_running_moments_merge_uneven_chunks():
    rows = np.random.default_rng(1).normal(3.0, 2.0, size=(1001, 3))
    moments = RunningMoments(3)
    for chunk in np.split(rows, [1, 2, 500, 500, 999]):  # includes an empty chunk and single rows
        moments.update(chunk)
    assert moments.count == 1001
    np.testing.assert_allclose(moments.mean, rows.mean(0), rtol=1e-12, atol=0)
    np.testing.assert_allclose(moments.std, rows.std(0), rtol=1e-12, atol=0)


def test_no_moving_particles_is_an_error():
    position = np.zeros((5, 4, 2), np.float32)
    with pytest.raises(ValueError, match="no trajectory with moving particles"):
        compute_statistics([(position, np.full(4, KINEMATIC))])
    with pytest.raises(ValueError, match="no trajectory with moving particles"):
        compute_statistics([])


# ---------------------------------------------------------------- the regime
def test_regime_counts_neighbours_and_the_energy_left():
    lattice = np.stack(np.meshgrid(np.arange(10), np.arange(10)), -1).reshape(-1, 2) * 0.01  # 100 particles
    still = np.repeat(lattice[None], 20, axis=0)  # [20, 100, 2], at rest
    moving = still + np.linspace(0, 1, 20)[:, None, None] ** 0.5  # decelerating drift
    for trajectory in (still, moving):
        result = regime(trajectory, np.full(100, WATER), radius=0.0105)
        # 4 neighbours inside, 3 on edges, 2 at corners: (64*4 + 32*3 + 4*2) / 100
        assert result["neighbours"] == pytest.approx([3.6] * 10)
    assert regime(still, np.full(100, WATER), 0.0105)["energy_left"] == 0.0
    left = regime(moving, np.full(100, WATER), 0.0105)["energy_left"]
    assert 0 < left < 0.3  # decelerating: the last 10 frames have less energy than the first


# water3d (WCSPH in 3D) at its own size takes ~17 s of a core per trajectory: here a scaled-down
# twin, a 0.28 m box with as many particles per floor area (pools of the same depth) and 300
# frames, enough to settle in the smaller box
WATER3D_SMALL = {"bounds": [[0.1, 0.38]] * 3, "particles": [250, 600], "body_size": [0.1, 0.19], "num_frames": 300}


@pytest.mark.parametrize("scene, least, overrides", [("waterdrop", 9.0, {}), ("waterramps", 9.0, {}), ("sand", 6.5, {}),
                                                     ("water3d", 9.0, WATER3D_SMALL)])
def test_default_scene_stays_in_waterdrop_regime(tmp_path, scene, least, overrides):
    """The default scene and the benchmarks made in its regime must form pools (or piles) that
    settle, not films one particle thick (mean neighbours ~5-6 in 2D, at most 8 in 3D) or water
    still sloshing at the end (docs/validation.md)."""
    cfg = {**scene_config(scene), **overrides}
    folder = generate_dataset(cfg, tmp_path / scene, num_trajectories=3, splits={"valid": 1, "test": 1},
                              workers=1, progress=False)
    metadata = read_metadata(folder)
    summary = metadata["regime"]
    assert summary["settled_neighbours_min"] >= least, summary
    assert summary["energy_left_max"] <= 0.15, summary
    with open_split(folder, "train") as train:
        assert all(position.shape[-1] == metadata["dim"] for position, _ in train)
        assert dataset_regime(train, metadata["default_connectivity_radius"])["settled_neighbours_min"] == \
            summary["settled_neighbours_min"]
    # deterministic: generated again, 10 frames long, the same trajectories' first 10 frames, bit for bit
    again = generate_dataset(cfg, tmp_path / "again", num_trajectories=3, num_frames=10,
                             splits={"valid": 1, "test": 1}, workers=1, progress=False)
    with open_split(folder, "train") as train, open_split(again, "train") as start:
        for (position, particle_type), (first, first_type) in zip(train, start, strict=True):
            assert np.array_equal(position[:10], first) and np.array_equal(particle_type, first_type)
