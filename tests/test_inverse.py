"""Inverse problems: the optimiser finds known answers and reports planted failures (goal shapes:
tests/test_goal.py)."""
import math

import numpy as np
import pytest
import torch

from rgns.data.contract import WATER
from rgns.data.scenes import lattice
from rgns.inverse.feedforward import feed_forward_inverse, forward_stability, inverse_stability
from rgns.inverse.optimise import StoppingRule, optimise_initial_state
from rgns.inverse.simulators import Ballistic, LearnedSimulator
from rgns.models import RGNS, State

SPACING = 0.0065
GRAVITY = torch.tensor([0.0, -9.81 * 0.0025**2])  # per frame squared


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)
    torch.manual_seed(0)


def blob(centre=(0.5, 0.5), side=6) -> torch.Tensor:
    lower = np.asarray(centre) - side * SPACING / 2
    return torch.as_tensor(lattice(lower, lower + side * SPACING, SPACING), dtype=torch.float32)


METADATA = dict(bounds=[[0.1, 0.9], [0.1, 0.9]], dim=2, default_connectivity_radius=0.015, dt=0.0025,
                vel_mean=[0.0, 0.0], vel_std=[1.3e-3, 1.3e-3], acc_mean=[0.0, 0.0], acc_std=[1e-4, 1e-4],
                generator=dict(params=dict(spacing=SPACING)))


# ---------------------------------------------------------------------------------------------- the optimiser
def test_ballistic_blob_recovers_the_known_initial_state():
    """A blob moving at a known velocity: with the target's velocity given, the answer is unique."""
    simulator = Ballistic(GRAVITY)
    x0 = blob()
    v0 = torch.tensor([2.0e-3, 1.0e-3]).expand_as(x0).clone()
    target_x, target_v = simulator.simulate(x0, v0, 10)
    result = optimise_initial_state(simulator, target_x, 10, target_velocity=target_v,
                                    rule=StoppingRule(max_iterations=400, abs_tol=1e-12, rel_tol=1e-4, window=20))
    assert result.status == "converged", result.reason
    assert result.loss < 1e-3 * result.loss_history[0]
    assert torch.allclose(result.initial_position, x0, atol=2e-4)
    assert torch.allclose(result.initial_velocity, v0, atol=2e-5)
    assert len(result.loss_history) == result.iterations and result.seconds > 0


def test_learned_simulator_untrained_rgns_is_constant_velocity_and_solvable():
    """An untrained R-GNS extrapolates at constant velocity: K steps from (p, V) reach p + K v_newest.
    Adam through its K steps (graph rebuilt per step, positions differentiated) finds such a state."""
    model = RGNS(METADATA, latent=16, layers=2)
    x0 = blob()
    particle_type = torch.full((len(x0),), WATER)
    simulator = LearnedSimulator(model, particle_type)
    history = torch.tensor([1.5e-3, -1.0e-3]).expand(len(x0), 5, 2).clone()
    target_x, target_v = simulator.simulate(x0, history, 4)
    assert torch.allclose(target_x, x0 + 4 * history[:, -1], atol=1e-6)  # constant velocity, as documented
    result = optimise_initial_state(simulator, target_x, 4, target_velocity=target_v,
                                    rule=StoppingRule(max_iterations=200, abs_tol=1e-11, rel_tol=1e-4, window=40))
    assert result.ok, result.reason
    assert result.loss < 1e-2 * result.loss_history[0]
    assert result.initial_velocity.shape == (len(x0), 5, 2)
    reached, _ = simulator.simulate(result.initial_position, result.initial_velocity, 4)
    assert (reached - target_x).pow(2).mean() < 1e-2 * (x0 + 0 - target_x).pow(2).mean() + 1e-12


def test_sph_short_horizon_loss_decreases():
    """Through the differentiable SPH at three frames: the loss goes down (no claim on gradient exactness)."""
    from rgns.inverse.simulators import SPHSimulator
    from rgns.physics.sph import SPHSolver

    simulator = SPHSimulator(SPHSolver(dim=2, capacity=64, spacing=SPACING, substeps=10))
    x0 = blob(side=6)
    v0 = torch.tensor([0.5, 0.0]).expand_as(x0) * 0.0025  # 0.5 m/s, per frame
    target, _ = simulator.simulate(x0, v0.clone(), 3)
    result = optimise_initial_state(simulator, target, 3, rule=StoppingRule(max_iterations=8))
    assert result.status in ("converged", "iteration_cap"), result.reason
    assert result.loss < 0.5 * result.loss_history[0]
    assert np.isfinite(result.loss_history).all()


# ---------------------------------------------------------------------------------------------- failure reports
class NaNGradient:
    """Forward is the ballistic one; the gradient is NaN."""

    class _Poison(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.clone()

        @staticmethod
        def backward(ctx, grad):
            return grad * math.nan

    def simulate(self, position, velocity, steps):
        position, velocity = Ballistic(GRAVITY).simulate(position, velocity, steps)
        return self._Poison.apply(position), velocity


class ExplodingGradient:
    """The chain through K frames multiplies the gradient by 10 per frame (a chaotic simulator)."""

    def simulate(self, position, velocity, steps):
        for _ in range(steps):
            position = 10.0 * position - 9.0 * position.detach() + velocity  # value unchanged, slope 10
        return position, velocity


class Drifting:
    """Each call moves the answer further away: the loss grows whatever the optimiser does."""

    def __init__(self):
        self.calls = 0

    def simulate(self, position, velocity, steps):
        self.calls += 1
        return position + velocity * steps + 0.01 * 2.0**self.calls, velocity


def test_failure_reported_on_nan_gradient():
    target = blob()
    result = optimise_initial_state(NaNGradient(), target + 0.01, 3, rule=StoppingRule(max_iterations=50))
    assert result.status == "failed" and "non-finite" in result.reason
    assert result.iterations == 1 and torch.isfinite(result.initial_position).all()


def test_failure_reported_on_exploding_gradient():
    target = blob()
    result = optimise_initial_state(ExplodingGradient(), target + 0.01, 12, init_position=target,
                                    rule=StoppingRule(max_iterations=50))
    assert result.status == "failed" and "exploding gradient" in result.reason
    assert result.grad_norm_history[-1] > StoppingRule().max_grad_norm


def test_failure_reported_on_divergence():
    target = blob()
    rule = StoppingRule(max_iterations=50, divergence_factor=10.0, patience=3)
    result = optimise_initial_state(Drifting(), target, 2, rule=rule)
    assert result.status == "failed" and "diverged" in result.reason
    assert result.iterations < 50
    assert result.loss == min(result.loss_history)  # the state returned is the best one, flagged failed


def test_iteration_cap_is_reported():
    simulator = Ballistic(GRAVITY)
    x0 = blob()
    target, _ = simulator.simulate(x0, torch.full_like(x0, 2e-3), 5)
    rule = StoppingRule(max_iterations=3, rel_tol=0.0)
    result = optimise_initial_state(simulator, target, 5, rule=rule)
    assert result.status == "iteration_cap" and result.iterations == 3
    assert result.loss <= result.loss_history[0]


# ---------------------------------------------------------------------------------------------- feed-forward, stability
def test_feed_forward_inverse_round_trip_and_stability():
    """Untrained R-GNS: K inverse steps from a constant-velocity state recover the earlier state
    exactly, and long rollouts of a blob report a finite stable length."""
    model = RGNS(METADATA, latent=16, layers=2)
    x0 = blob()
    particle_type = torch.full((len(x0),), WATER)
    v = torch.tensor([1e-3, 0.0])
    positions = torch.stack([x0 + t * v for t in range(30)])  # [T, N, D], constant velocity
    state = State.from_positions(positions[24:30], particle_type)
    result, inferred = feed_forward_inverse(model, state, 10)
    assert result.status == "feed_forward" and result.seconds > 0
    assert torch.allclose(result.initial_position, positions[19], atol=1e-5)
    assert inferred.shape == (10, len(x0), 2)
    forward = forward_stability(model, positions, particle_type, start=5, steps=600, chunk=50)
    # constant velocity 1e-3 per frame from x ~ 0.52: leaves the box (0.9 + 2 R) after ~ 410 steps
    assert forward["diverged"] and 350 < forward["stable_steps"] < 450
    backward = inverse_stability(model, positions, particle_type, end=29, steps=200, chunk=50)
    assert not backward["diverged"] and backward["stable_steps"] == 200


# ---------------------------------------------------------------------------------------------- MLS-MPM in torch
def test_torch_mpm_follows_the_taichi_solver_and_optimises():
    """The differentiable MLS-MPM port matches rgns.physics.mpm.MPMSolver on a block that hits the
    floor, and Adam through it lowers the loss at a short horizon."""
    from rgns.inverse.mpm import TorchMPM
    from rgns.physics.mpm import MPMSolver

    x0 = lattice(np.array([0.4, 0.11]), np.array([0.45, 0.16]), SPACING).astype(np.float32)
    v0 = np.tile([0.5, -1.0], (len(x0), 1)).astype(np.float32)  # m/s: reaches the floor in ~4 frames
    truth = MPMSolver(dim=2, capacity=len(x0)).rollout(x0, v0, np.full(len(x0), WATER), 13)
    free_fall = x0[:, 1].min() - 12 * 0.0025 * 1.0  # where the lowest particle would be without the floor
    assert free_fall < 0.09 and 0.1 <= truth[-1, :, 1].min() < 0.11  # the floor stopped the block
    simulator = TorchMPM()
    ours = simulator.trajectory(torch.as_tensor(x0), torch.as_tensor(v0) * 0.0025, 12).numpy()
    assert np.abs(ours - truth).max() < 1e-5
    target, _ = simulator.simulate(torch.as_tensor(x0), torch.as_tensor(v0) * 0.0025, 2)
    result = optimise_initial_state(simulator, target, 2, rule=StoppingRule(max_iterations=6))
    assert result.ok and result.loss < 0.5 * result.loss_history[0], result.reason


def test_torch_mpm_puts_a_start_outside_the_box_on_its_walls():
    """An optimiser's iterate can leave the box; the port starts it on the walls (as each substep puts
    back a particle that crossed one) instead of indexing past its grid."""
    from rgns.inverse.mpm import TorchMPM

    simulator = TorchMPM()  # box [0.1, 0.9]^2, 3 cells of grid margin
    inside = lattice(np.array([0.4, 0.4]), np.array([0.45, 0.45]), SPACING).astype(np.float32)
    start = torch.as_tensor(inside)
    start[0] = torch.tensor([-0.2, 0.5])  # 0.3 m (19 cells) left of the wall: past the grid
    start[1] = torch.tensor([0.5, 1.3])  # above the ceiling
    frames = simulator.trajectory(start, torch.zeros_like(start), 2)
    assert torch.isfinite(frames).all()
    assert frames[0, 0].tolist() == pytest.approx([0.1, 0.5]) and frames[0, 1].tolist() == pytest.approx([0.5, 0.9])
    assert (frames[-1] >= 0.1).all() and (frames[-1] <= 0.9).all()
