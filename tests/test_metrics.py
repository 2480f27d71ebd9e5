import math

import pytest
import torch
from conftest import make_metadata

from rgns.evaluation.metrics import chamfer, divergence_step, mmd, mse_per_step, optimal_transport, rollout_mse
from rgns.training.losses import LossDesign


@pytest.fixture
def points():
    torch.manual_seed(0)
    return torch.rand(200, 2)


def test_identical_sets_score_zero(points):
    assert rollout_mse(points[None], points[None]) == 0.0
    assert optimal_transport(points, points) == pytest.approx(0.0, abs=1e-12)
    assert mmd(points, points, scale=0.05) == pytest.approx(0.0, abs=1e-12)
    assert chamfer(points, points) == 0.0


def test_shifted_set(points):
    d = torch.tensor([0.03, -0.04])  # |d|^2 = 0.0025
    shifted = points + d
    assert rollout_mse(shifted[None], points[None]) == pytest.approx(0.0025 / 2)  # mean over dims
    assert optimal_transport(shifted, points) == pytest.approx(0.0025, rel=1e-6)


def test_permutation_does_not_change_ot_but_changes_mse(points):
    permuted = points[torch.randperm(len(points))]
    assert optimal_transport(permuted, points) == pytest.approx(0.0, abs=1e-12)
    assert rollout_mse(permuted[None], points[None]) > 1e-2


def test_mmd_separates_distributions():
    torch.manual_seed(1)
    a, b = torch.rand(400, 2), torch.rand(400, 2)
    c = torch.rand(400, 2) * 0.5  # another distribution
    same, different = mmd(a, b, scale=0.2), mmd(a, c, scale=0.2)
    assert same < 0.02
    assert different > 10 * same


def test_mse_per_step_shape_and_values():
    truth = torch.zeros(4, 10, 3)
    predicted = truth + torch.arange(4.0)[:, None, None]
    assert mse_per_step(predicted, truth).tolist() == [0.0, 1.0, 4.0, 9.0]


def test_divergence_step_finds_each_failure():
    bounds = torch.tensor([[0.0, 1.0], [0.0, 1.0]])
    calm = 0.5 + 0.001 * torch.arange(10.0)[:, None, None].expand(10, 5, 2)
    assert divergence_step(calm, bounds, margin=0.05, reference_speed=0.001) is None
    nan = calm.clone()
    nan[6, 2, 0] = math.nan
    assert divergence_step(nan, bounds, margin=0.05, reference_speed=0.001) == 6
    out = calm.clone()
    out[4:, 0, 1] = 1.2
    assert divergence_step(out, bounds, margin=0.05, reference_speed=0.001) == 4
    fast = calm.clone()
    fast[7:] += torch.arange(3.0)[:, None, None] * 0.05 + 0.05  # a jump of 0.05/frame >> 0.001
    assert divergence_step(fast, bounds, margin=0.5, reference_speed=0.001) == 7


def test_loss_designs_weigh_their_terms():
    torch.manual_seed(0)
    change, target = torch.randn(50, 2), torch.randn(50, 2)
    batch = torch.zeros(50, dtype=torch.long)
    dl4 = LossDesign("DL4")(change, target, batch)
    assert set(dl4) == {"mse", "loss"}
    assert dl4["loss"] == pytest.approx(float(((change - target) ** 2).mean()))
    dl2 = LossDesign("DL2", cosine=0.1, mmd=0.1)(change, target, batch)
    assert set(dl2) == {"mse", "cosine", "mmd", "loss"}
    expected = dl2["mse"] + 0.1 * dl2["cosine"] + 0.1 * dl2["mmd"]
    assert float(dl2["loss"]) == pytest.approx(float(expected))
    assert float(dl2["cosine"]) > 0 and float(dl2["mmd"]) > 0
    perfect = LossDesign("DL2", cosine=0.1, mmd=0.1)(target, target, batch)
    assert float(perfect["loss"]) == pytest.approx(0.0, abs=1e-6)


def free_fall(frames: int = 40, particles: int = 12):
    """Particles in free flight in the middle of the box (no wall reached): ``[T, N, 2]`` and the
    metadata of a scene with gravity."""
    metadata = dict(make_metadata(), gravity=[0.0, -9.81])
    g = torch.tensor([0.0, -9.81]) * metadata["dt"] ** 2  # per frame squared
    start = 0.4 + 0.2 * torch.rand(particles, 2, generator=torch.Generator().manual_seed(0))
    velocity = 1e-3 * torch.randn(particles, 2, generator=torch.Generator().manual_seed(1))
    t = torch.arange(frames, dtype=torch.float64)[:, None, None]
    position = start.double() + velocity.double() * t + 0.5 * g.double() * t**2
    return position.float(), torch.full((particles,), 5), metadata, g


def test_one_step_diagnostic_finds_gravity_missing_and_present():
    """Ballistic motion predicts a free fall's acceleration exactly; constant velocity misses all
    of it (an error of |g|, relative error 1)."""
    from rgns.evaluation.baselines import Ballistic, ConstantVelocity
    from rgns.evaluation.onestep import by_span, one_step_accelerations

    position, particle_type, metadata, g = free_fall()
    for model, expected in ((Ballistic(metadata), 0.0), (ConstantVelocity(metadata), 1.0)):
        accelerations = one_step_accelerations(model, position, particle_type)
        assert accelerations["frame"].tolist() == list(range(5, 39))
        rows = by_span([accelerations], spans=(5, 20))
        assert [r["frames"] for r in rows] == ["5-20", "20-end"]
        for row in rows:
            assert row["true_rms"] == pytest.approx(float(g.norm()), rel=1e-2)
            assert row["relative_error"] == pytest.approx(expected, abs=1e-2)
