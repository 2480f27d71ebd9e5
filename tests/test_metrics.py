import json
import math

import pytest
import torch
from conftest import make_metadata

from rgns.evaluation.metrics import (chamfer, divergence_step, mmd, mse_per_step, optimal_transport, rollout_mse,
                                    with_last)
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


def test_with_last_appends_the_last_step_once():
    assert with_last([25, 50], 60) == [25, 50, 60]
    assert with_last([25, 50], 50) == [25, 50]
    assert with_last([], 7) == [7]


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


def write_results(folder, per_trajectory: dict[str, list[float]], dataset="data", split="test", baselines=()):
    """A results.json of evaluate.py's shape holding only what the comparison reads."""
    folder.mkdir(parents=True, exist_ok=True)
    methods = {label: {"rollout_mse_per_trajectory": v} for label, v in per_trajectory.items()}
    results = {"methods": {label: {"source": "baseline" if label in baselines else "model.ckpt"} for label in per_trajectory},
               "datasets": {dataset: {"split": split, "forward": {"methods": methods}}}}
    (folder / "results.json").write_text(json.dumps(results))
    return folder


def test_compare_pairs_trajectories_and_pools_splits(tmp_path, capsys):
    from rgns.evaluation.compare import main

    reference = [1.0, 4.0, 2.0, 8.0]
    test_a = write_results(tmp_path / "a_test", {"A": reference, "Const. velocity": [9.0] * 4}, baselines={"Const. velocity"})
    test_b = write_results(tmp_path / "b_test", {"B": [2 * x for x in reference]})  # twice A's error on every trajectory
    test_c = write_results(tmp_path / "c_test", {"C": [0.5, 6.0, 1.0, 9.0]})
    sel_a = write_results(tmp_path / "a_sel", {"A": [3.0, 1.0]}, split="selection")
    sel_b = write_results(tmp_path / "b_sel", {"B": [6.0, 2.0]}, split="selection")
    rows = main([f"A={test_a}", f"B={test_b}/results.json", f"C={test_c}", "--resamples", "2000"])
    a, b, c = rows
    assert "ratio" not in a and a["mean"] == pytest.approx(3.75)
    # every trajectory twice the reference's: every resample's ratio is 2, so the interval is [2, 2]
    assert (b["ratio"], b["low"], b["high"], b["lower"], b["higher"]) == (pytest.approx(2), pytest.approx(2),
                                                                            pytest.approx(2), 0, 4)
    assert c["ratio"] == pytest.approx(16.5 / 15) and c["low"] < 1 < c["high"] and (c["lower"], c["higher"]) == (2, 2)
    assert "| B | 1 | 4 | 7500 |  | 2.000 | 2.000-2.000 | 0 / 4 |" in capsys.readouterr().out
    # two splits pooled per name: six trajectories, still twice on each
    (a, b) = main([f"A={test_a},{sel_a}", f"B={sel_b},{test_b}", "--reference", "B", "--resamples", "100"])
    assert a["trajectories"] == 6 and a["ratio"] == pytest.approx(0.5) and a["high"] == pytest.approx(0.5)


def test_compare_averages_seeds_and_resamples_them(tmp_path, capsys):
    """Seeds joined by + are averaged per trajectory, and the interval carries their spread: a
    method whose two seeds score 2x and 4x the reference everywhere is 3x, with an interval from 2
    to 4 (the resamples that draw one seed twice), not the single point 3."""
    from rgns.evaluation.compare import main

    reference = [1.0, 4.0, 2.0, 8.0]
    ref = write_results(tmp_path / "ref", {"R": reference})
    s0 = write_results(tmp_path / "s0", {"M s0": [2 * x for x in reference]})
    s1 = write_results(tmp_path / "s1", {"M s1": [4 * x for x in reference]})
    _, m = main([f"R={ref}", f"M={s0}+{s1}", "--resamples", "4000"])
    assert (m["seeds"], m["trajectories"]) == (2, 4)
    assert m["ratio"] == pytest.approx(3) and m["low"] == pytest.approx(2) and m["high"] == pytest.approx(4)
    assert m["seed_means"] == pytest.approx([7.5, 15.0]) and m["seed_std"] == pytest.approx(7.5 / 2 ** 0.5)
    assert (m["lower"], m["higher"]) == (0, 4)
    assert "| M | 2 | 4 | 1.125e+04 | 5303 | 3.000 | 2.000-4.000 | 0 / 4 |" in capsys.readouterr().out
    # pooled splits keep each seed's files together: seed 0 is 2x on both splits, seed 1 4x
    ref_sel = write_results(tmp_path / "ref_sel", {"R": [2.0, 2.0]}, split="selection")
    s0_sel = write_results(tmp_path / "s0_sel", {"M": [4.0, 4.0]}, split="selection")
    s1_sel = write_results(tmp_path / "s1_sel", {"M": [8.0, 8.0]}, split="selection")
    _, m = main([f"R={ref},{ref_sel}", f"M={s0}+{s1},{s0_sel}+{s1_sel}", "--resamples", "100"])
    assert m["trajectories"] == 6 and m["seed_means"] == pytest.approx([38 / 6, 76 / 6]) and m["ratio"] == pytest.approx(3)
    # a method of several seeds as the reference: the others' ratios are to its seeds' mean
    _, r = main([f"M={s0}+{s1}", f"R={ref}", "--resamples", "100"])
    assert r["ratio"] == pytest.approx(1 / 3) and r["low"] == pytest.approx(1 / 4) and r["high"] == pytest.approx(1 / 2)


def test_compare_refuses_what_it_cannot_pair(tmp_path):
    from rgns.evaluation.compare import CompareError, main

    four = write_results(tmp_path / "four", {"A": [1.0, 2.0, 3.0, 4.0]})
    three = write_results(tmp_path / "three", {"B": [1.0, 2.0, 3.0]})
    other_split = write_results(tmp_path / "valid", {"B": [1.0, 2.0, 3.0, 4.0]}, split="valid")
    two_models = write_results(tmp_path / "two", {"R-GNS": [1.0] * 4, "GNS": [2.0] * 4})
    with pytest.raises(CompareError, match="B has 3 trajectories of data"):
        main([f"A={four}", f"B={three}"])
    with pytest.raises(CompareError, match="compare like with like"):
        main([f"A={four}", f"B={other_split}"])
    with pytest.raises(CompareError, match=r"two/results.json: data holds 2 methods .*RESULTS#LABEL"):
        main([f"A={four}", f"B={two_models}"])
    assert main([f"A={four}", f"B={two_models}#GNS", "--resamples", "10"])[1]["ratio"] == pytest.approx(0.8)
    with pytest.raises(CompareError, match="no method 'EGNN'"):
        main([f"A={four}", f"B={two_models}#EGNN"])
    with pytest.raises(CompareError, match="nowhere: no results.json"):
        main([f"A={four}", f"B={tmp_path / 'nowhere'}"])
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "results.json").write_text("{")
    with pytest.raises(CompareError, match="broken/results.json: not an evaluate.py results.json"):
        main([f"A={four}", f"B={tmp_path / 'broken'}"])
    with pytest.raises(CompareError, match="--reference Z"):
        main([f"A={four}", "--reference", "Z"])
    # seeds joined by + must hold the same trajectories; a name's splits the same number of seeds
    with pytest.raises(CompareError, match=r"B: .*three/results.json has 3 trajectories of data \(test\), .*four/results.json 4"):
        main([f"A={four}", f"B={four}+{three}"])
    with pytest.raises(CompareError, match=r"valid/results.json and .*four/results.json .* do not both hold data \(test\)"):
        main([f"A={four}", f"B={four}+{other_split}"])
    sel = write_results(tmp_path / "sel", {"A": [1.0]}, split="selection")
    with pytest.raises(CompareError, match="B: its splits have different numbers of seeds"):
        main([f"A={four},{sel}", f"B={four}+{four},{sel}"])
