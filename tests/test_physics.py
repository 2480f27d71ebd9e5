"""Ground-truth solvers: conservation, walls, obstacles, and validation against experiments.

The dam-break and resting-tank checks are the ones ``docs/validation.md`` reports.
"""
import numpy as np
import pytest

from rgns.data.contract import SAND, WATER
from rgns.data.scenes import lattice
from rgns.physics import Capsule
from rgns.physics.validation import G, dam_break, dam_break_errors, hydrostatic_profile, resting_tank


@pytest.fixture(scope="module")
def mpm():
    from rgns.physics.mpm import MPMSolver

    return MPMSolver(dim=2, capacity=4096, n_grid=64, bounds=((0.1, 0.9), (0.1, 0.9)))


def test_free_fall_follows_gravity(mpm):
    position = lattice(np.array([0.4, 0.6]), np.array([0.46, 0.66]), 0.0065)
    velocity = np.tile([0.5, 0.0], (len(position), 1))
    trajectory = mpm.rollout(position, velocity, np.full(len(position), WATER), 41)  # 0.1 s
    drop = position[:, 1].mean() - trajectory[-1, :, 1].mean()
    assert drop == pytest.approx(0.5 * G * 0.1**2, rel=0.02)
    assert trajectory[-1, :, 0].mean() - position[:, 0].mean() == pytest.approx(0.05, rel=0.02)
    assert trajectory.shape == (41, len(position), 2) and trajectory.dtype == np.float32


def test_walls_and_ramps_hold_every_particle(mpm):
    ramp = Capsule((0.3, 0.45), (0.7, 0.3), 0.0065)
    position = lattice(np.array([0.35, 0.55]), np.array([0.5, 0.7]), 0.0065)
    velocity = np.tile([0.5, -1.0], (len(position), 1))
    trajectory = mpm.rollout(position, velocity, np.full(len(position), WATER), 161, obstacles=[ramp])
    assert np.isfinite(trajectory).all() and trajectory.shape[1] == len(position)
    assert trajectory.min() >= np.float32(0.1) and trajectory.max() <= np.float32(0.9)
    distance = ramp.signed_distance(trajectory.reshape(-1, 2).astype(float)).reshape(trajectory.shape[:2])
    assert distance.min() > -1e-5
    # the water did land on the ramp: most particles touched it (within two spacings) at some frame
    assert (distance < 0.013).any(0).mean() > 0.5


def test_sand_piles_where_water_spreads(mpm):
    column = lattice(np.array([0.1, 0.1]), np.array([0.2, 0.3]), 0.0065)
    still = np.zeros_like(column)
    water = mpm.rollout(column, still, np.full(len(column), WATER), 201)[-1]
    mpm.wall_friction = 0.5  # a rough floor
    try:
        sand = mpm.rollout(column, still, np.full(len(column), SAND), 201)[-1]
    finally:
        mpm.wall_friction = 0.0
    assert water[:, 0].max() > 0.7  # water ran across the floor
    assert sand[:, 0].max() < 0.45  # sand slumped into a pile
    assert sand[:, 1].max() > 0.15  # ... that still stands
    final_speed = np.linalg.norm(mpm.velocities(), axis=1).max()
    assert final_speed < 0.05  # and has stopped


def test_mpm_dam_break_matches_martin_moyce(mpm):
    T, Z = dam_break(mpm, width=0.156, spacing=0.0065, num_frames=140)
    errors = dam_break_errors(T, Z)
    assert np.abs(errors).max() < 0.20, errors


def test_mpm_resting_tank_stays_at_rest(mpm):
    depth = 0.12
    trajectory = resting_tank(mpm, depth=depth, spacing=0.008, num_frames=401)  # hydrostatic start
    speed = np.linalg.norm(np.diff(trajectory[-41:], axis=0), axis=-1) / 0.0025  # the last 0.1 s
    assert speed.max() < 0.01 * np.sqrt(G * depth)
    assert trajectory.min() >= np.float32(0.1) and np.isfinite(trajectory).all()


@pytest.fixture(scope="module")
def sph():
    from rgns.physics.sph import SPHSolver

    return SPHSolver(dim=2, capacity=4096, spacing=0.0065)


@pytest.mark.slow
def test_sph_dam_break_matches_martin_moyce(sph):
    T, Z = dam_break(sph, width=0.156, spacing=0.0065, num_frames=140)
    errors = dam_break_errors(T, Z)
    assert np.abs(errors).max() < 0.20, errors


@pytest.mark.slow
def test_sph_resting_tank_stays_at_rest_with_hydrostatic_pressure(sph):
    """From an uncompressed lattice: settled after 1.8 s, and the pressure grows as rho0 g depth
    (Adami, Hu & Adams 2012) below the free surface's kernel-deficient layer."""
    depth, spacing = 0.12, 0.0065
    trajectory = resting_tank(sph, depth=depth, spacing=spacing, num_frames=801, hydrostatic=False)
    speed = np.linalg.norm(np.diff(trajectory[-41:], axis=0), axis=-1) / 0.0025  # the last 0.1 s
    assert speed.max() < 0.01 * np.sqrt(G * depth)
    assert trajectory.min() >= np.float32(0.1) and np.isfinite(trajectory).all()
    T, P = hydrostatic_profile(trajectory[-1], sph.pressures(), spacing, bins=6)
    assert (np.diff(P) > 0).all(), P  # pressure grows with depth
    deep = T > 2.4 * spacing  # below the top kernel support, where the summed density is whole
    np.testing.assert_allclose(P[deep], 1000.0 * G * T[deep], rtol=0.1)


def test_sph_free_fall_and_gradient_shapes():
    from rgns.physics.sph import SPHSolver

    solver = SPHSolver(dim=2, capacity=64, spacing=0.0065, substeps=10, dtype="f64")
    position = lattice(np.array([0.4, 0.5]), np.array([0.44, 0.54]), 0.0065)  # 36 particles
    velocity = np.zeros_like(position)
    final, final_velocity = solver.forward(position, velocity, 8)  # 0.02 s, before any impact
    assert final[:, 1].mean() - position[:, 1].mean() == pytest.approx(-0.5 * G * 0.02**2, rel=0.05)
    grad_x, grad_v = solver.backward(np.ones_like(final))
    assert grad_x.shape == grad_v.shape == position.shape and np.isfinite(grad_v).all()
    # d(sum of final x) / d(initial v) is ~ the elapsed time for each particle in free flight
    assert grad_v.sum(0) == pytest.approx(np.full(2, 0.02 * len(position)), rel=0.1)


@pytest.mark.parametrize("corner", [(0.4, 0.5), (0.1, 0.1)], ids=["free-flight", "in-a-corner"])
def test_sph_gradient_matches_finite_differences(corner):
    """Reverse-mode gradients of a weighted sum of the final positions (6 frames, 15 ms) against
    central differences in float64: per component of the initial velocity and along a random
    direction of the initial positions. In the corner the wall kernels (Adami's pressure) are in play."""
    from rgns.physics.sph import SPHSolver

    solver = SPHSolver(dim=2, capacity=64, spacing=0.0065, substeps=10, dtype="f64")
    rng = np.random.default_rng(0)
    lower = np.array(corner)
    # jittered off the lattice: a lattice at rest sits exactly on the kink of the clamped pressure
    position = lattice(lower, lower + 0.04, 0.0065) + rng.uniform(-3e-4, 3e-4, (36, 2))
    position = np.clip(position, 0.1, 0.9)
    velocity = rng.normal(0, 0.3, position.shape)
    weights = rng.normal(size=position.shape)
    solver.forward(position, velocity, 6)
    grad_x, grad_v = solver.backward(weights)

    def loss(x, v):
        return float((solver.forward(x, v, 6)[0] * weights).sum())

    for i, d in [(0, 0), (7, 1), (20, 0), (35, 1)]:
        step = np.zeros_like(velocity)
        step[i, d] = 1e-6
        finite_difference = (loss(position, velocity + step) - loss(position, velocity - step)) / 2e-6
        assert grad_v[i, d] == pytest.approx(finite_difference, rel=1e-5)
    direction = rng.normal(size=position.shape)
    finite_difference = (loss(position + 1e-8 * direction, velocity) - loss(position - 1e-8 * direction, velocity)) / 2e-8
    assert (grad_x * direction).sum() == pytest.approx(finite_difference, rel=1e-4)
