"""Where methods fail: the break classifier names each planted failure, each condition builds the
scene it names, deterministically, and the task rolls methods out on them."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from rgns.data.contract import KINEMATIC, WATER
from rgns.data.generate import generate_dataset, scene_config
from rgns.evaluation.baselines import ConstantVelocity
from rgns.evaluation.generalise import BreakRule, Generalisation, classify_break, condition_scene, densest_cells
from rgns.evaluation.methods import Method
from rgns.evaluation.tasks import Dataset

BOUNDS = torch.tensor([[0.0, 1.0], [0.0, 1.0]])
RADIUS = 0.05


def drifting(frames: int = 80, side: int = 10, speed: float = 1e-3) -> torch.Tensor:
    """A lattice of side x side particles over [0.2, 0.8]^2 drifting right at ``speed`` per frame.  [T, N, 2]"""
    axis = torch.linspace(0.2, 0.8, side)
    lattice = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    steps = torch.arange(frames, dtype=torch.float32).view(-1, 1, 1)
    return lattice.unsqueeze(0) + steps * torch.tensor([speed, 0.0])


def classify(predicted, truth, particle_type=None):
    particle_type = torch.full((truth.shape[1],), WATER) if particle_type is None else particle_type
    return classify_break(predicted, truth, particle_type, BOUNDS, RADIUS, BreakRule(), before=truth[0])


def test_a_rollout_that_follows_the_truth_never_breaks():
    truth = drifting()
    noisy = truth + 1e-5 * torch.randn(truth.shape, generator=torch.Generator().manual_seed(0))
    assert classify(noisy, truth) == (None, None)


def test_a_nan_breaks_at_its_frame():
    truth = drifting()
    predicted = truth.clone()
    predicted[7, 3, 1] = float("nan")
    assert classify(predicted, truth) == (7, "non-finite")


def test_leaving_the_box_breaks_where_a_particle_is_two_radii_out():
    truth = drifting()
    predicted = truth.clone()
    predicted[:, 5, 0] = 0.2 + 0.0199 * torch.arange(len(truth))  # one particle runs off to the right
    expected = int((predicted[:, 5, 0] > 1.0 + 2 * RADIUS).nonzero()[0])
    assert bool(predicted[expected - 1, 5, 0] > 1.0)  # out the frame before, but within the margin
    assert classify(predicted, truth) == (expected, "left the box")


def test_a_kinematic_particle_outside_breaks_nothing():
    truth = drifting()
    particle_type = torch.full((truth.shape[1],), WATER)
    particle_type[0] = KINEMATIC
    predicted = truth.clone()
    predicted[:, 0] = 5.0
    truth = truth.clone()
    truth[:, 0] = 5.0
    assert classify(predicted, truth, particle_type) == (None, None)


def test_jitter_in_the_box_is_an_explosion():
    truth = drifting()
    predicted = truth.clone()
    sign = torch.tensor([(-1.0) ** t for t in range(len(truth))]).view(-1, 1, 1)
    predicted[12:] += 0.1 * sign[12:]
    assert classify(predicted, truth) == (12, "exploded")


def test_water_squeezed_into_a_clump_is_compressed():
    truth = drifting()
    centre = truth.mean(1, keepdim=True)
    scale = torch.linspace(1.0, 0.01, 50).tolist() + [0.01] * 30
    predicted = centre + (truth - centre) * torch.tensor(scale).view(-1, 1, 1)
    step, cause = classify(predicted, truth)
    assert cause == "compressed" and 0 < step < 50  # while it contracts
    densest = densest_cells(predicted, BOUNDS[:, 0], RADIUS)
    assert densest[step] > 3 * int(densest_cells(truth, BOUNDS[:, 0], RADIUS).max()) >= densest[step - 1]


def test_water_that_stops_while_the_truth_moves_has_stalled():
    truth = drifting(speed=2e-3)
    predicted = truth.clone()
    predicted[10:] = predicted[9]
    step, cause = classify(predicted, truth)
    assert cause == "stalled" and 5 <= step <= 10


def test_settling_water_is_not_stalled():
    """The truth slows to rest: a rollout that rests with it has not stalled."""
    speed = torch.cat([torch.full((30,), 2e-3), torch.zeros(50)])
    truth = drifting(frames=1)[0] + torch.cumsum(speed, 0).view(-1, 1, 1) * torch.tensor([1.0, 0.0])
    assert classify(truth.clone(), truth) == (None, None)


WATERDROP = scene_config("waterdrop")


@pytest.mark.parametrize("name", ["longer", "wide_box", "more_bodies", "full"])
def test_each_condition_builds_the_scene_it_names(name):
    cfg, what = condition_scene(name, WATERDROP, steps=1000, start=5)
    assert isinstance(what, str) and what
    if name == "longer":
        assert cfg == WATERDROP
    if name == "wide_box":
        assert cfg["bounds"] == [[0.1, 0.9], [0.1, 0.5]] and WATERDROP["bounds"] == [[0.1, 0.5], [0.1, 0.5]]
    if name == "more_bodies":
        assert cfg["num_bodies"] == [2, 4] and cfg["particles"] == [300, 1200]
    if name == "full":
        assert cfg["name"] == "waterdrop_full" and cfg["bounds"] == [[0.1, 0.9], [0.1, 0.9]]


def test_ramps_outside_the_training_range_only_where_there_are_ramps():
    ramps = scene_config("waterramps")
    cfg, _ = condition_scene("ramps_outside", ramps, steps=10, start=5)
    assert cfg["ramp_angle"][0] > ramps["ramp_angle"][1]
    assert condition_scene("ramps_outside", WATERDROP, steps=10, start=5)[0] is None
    with pytest.raises(ValueError, match="unknown condition"):
        condition_scene("upside_down", WATERDROP, steps=10, start=5)


def test_a_condition_is_generated_the_same_twice(tmp_path):
    cfg, _ = condition_scene("wide_box", WATERDROP, steps=6, start=5)
    splits = {"train": 1, "valid": 1, "test": 1}
    roots = [generate_dataset(cfg, tmp_path / f"copy{i}", num_frames=12, seed=7, workers=1, progress=False,
                              splits=splits) for i in range(2)]
    with h5py.File(roots[0] / "test.h5") as a, h5py.File(roots[1] / "test.h5") as b:
        key = sorted(a.keys())[0]
        assert np.array_equal(a[key]["position"][()], b[key]["position"][()])
        assert a[key]["position"][()][..., 0].max() > 0.5  # bodies drawn across the wide box


def test_the_task_rolls_methods_out_on_each_condition_in_its_box(tmp_path):
    cfg = scene_config("waterdrop")
    cfg["splits"] = {"train": 1, "valid": 1, "test": 1}
    root = generate_dataset(cfg, tmp_path / "waterdrop", num_frames=14, seed=3, workers=1, progress=False)
    dataset = Dataset.load(str(root), "test", 1, 5, None)
    seen = []

    class Recording(ConstantVelocity):
        def step(self, state, *args, **kwargs):
            seen.append(self.bounds.clone())
            return super().step(state, *args, **kwargs)

    method = Method("Const. velocity", Recording(dataset.metadata, history=5), None, "baseline")
    task = Generalisation(str(tmp_path / "out"), conditions=["longer", "wide_box", "ramps_outside"], trajectories=1,
                          steps=8, references={"resolutions": [0.5], "floor_perturbation": None})
    results, examples = task([method], dataset)
    conditions = results["conditions"]
    assert "no ramps" in conditions["ramps_outside"]["skipped"]
    for name in ("longer", "wide_box"):
        rows = conditions[name]["methods"]
        assert set(rows) == {"Const. velocity", "MPM 32 cells/m"}
        assert len(rows["Const. velocity"]["mse_per_step"]) == 8
        assert rows["MPM 32 cells/m"]["rollout_mse"] < rows["Const. velocity"]["rollout_mse"]
        assert (tmp_path / "out" / "conditions" / f"waterdrop_{name}" / "test.h5").is_file()
    assert torch.allclose(seen[-1], torch.tensor([[0.1, 0.9], [0.1, 0.5]]))  # the wide box's walls while rolling out there
    assert torch.allclose(method.model.bounds, torch.tensor([[0.1, 0.5], [0.1, 0.5]]))  # and back
    at, frame = examples["wide_box"]["predicted"]["Const. velocity"]
    assert frame.shape[1] == 2 and 0 <= at < 8


def test_evaluate_task_generalise_writes_the_table_and_the_charts(tmp_path, monkeypatch):
    """evaluate.py task=generalise: a stand-in checkpoint, the baselines and the half-grid solver on
    two conditions; the report's cells are what results.json holds."""
    from test_evaluate import markdown_tables
    from test_references import stand_in_config, tiny

    import rgns.evaluation.run as run_module
    generated = tiny("waterdrop", _Factory(tmp_path), frames=14, test=1)
    cfg = stand_in_config(generated, monkeypatch, [
        "task=generalise", f"output_dir={tmp_path / 'out'}", "trajectories=1", "task.generalise.steps=6",
        "task.generalise.trajectories=1", "task.generalise.conditions=[longer,wide_box]", "animation.max_frames=2"])
    run_module.evaluate(cfg)
    out = tmp_path / "out"
    import json
    section = json.loads((out / "results.json").read_text())["datasets"][generated.name]["generalise"]
    rows = section["conditions"]["wide_box"]["methods"]
    assert {"GNS 8x1", "Const. velocity", "Ballistic + walls", "MPM 32 cells/m"} <= set(rows)
    table = markdown_tables((out / "report.md").read_text())[f"Where methods fail on {generated.name}"]
    assert table["Method"] == ["longer", "wide_box"]
    cell = table["GNS 8x1"][1]
    assert cell.startswith(f"{rows['GNS 8x1']['rollout_mse'] * 1e3:.4g} / {rows['GNS 8x1']['stable_steps']}")
    for name in (f"generalise_{generated.name}.png", f"generalise_{generated.name}_wide_box.png"):
        assert (out / name).stat().st_size > 0


class _Factory:
    """tmp_path_factory's mktemp over one test's tmp_path."""

    def __init__(self, root):
        self.root = root

    def mktemp(self, name):
        path = self.root / name
        path.mkdir()
        return path
