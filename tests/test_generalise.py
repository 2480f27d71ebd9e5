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
from rgns.evaluation.generalise import (HALF_GRID, BreakRule, Generalisation, break_picture, classify_break,
                                      condition_scene, densest_cells, inverse_rollout)
from rgns.evaluation.methods import Method
from rgns.evaluation.plots import up_axis
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


@pytest.fixture(scope="module")
def waterdrop_test(tmp_path_factory) -> Dataset:
    """A generated waterdrop test split of one 14-frame trajectory, from frame 5."""
    cfg = scene_config("waterdrop")
    cfg["splits"] = {"train": 1, "valid": 1, "test": 1}
    root = generate_dataset(cfg, tmp_path_factory.mktemp("data") / "waterdrop", num_frames=14, seed=3, workers=1,
                            progress=False)
    return Dataset.load(str(root), "test", 1, 5, None)


def test_the_task_rolls_methods_out_on_each_condition_in_its_box(tmp_path, waterdrop_test):
    dataset = waterdrop_test
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


def test_no_references_means_no_solver_run(tmp_path, monkeypatch, waterdrop_test):
    """references=None (what rgns.failures asks of each run's evaluation: it measures the solver
    once per benchmark) rolls out the methods alone; the default is the solver at half its grid."""
    import rgns.evaluation.references as references_module

    dataset = waterdrop_test
    method = Method("Const. velocity", ConstantVelocity(dataset.metadata, history=5), None, "baseline")
    built = []
    real = references_module.SolverReferences

    class Counting(real):
        def __init__(self, *args, **kwargs):
            built.append(kwargs)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(references_module, "SolverReferences", Counting)
    for references, rows in ((None, {"Const. velocity"}), ({}, {"Const. velocity"}),
                             (HALF_GRID, {"Const. velocity", "MPM 32 cells/m"})):
        task = Generalisation(str(tmp_path / "out"), conditions=["longer"], trajectories=1, steps=4,
                              directions=["forward"], references=references)
        results, _ = task([method], dataset)
        assert set(results["conditions"]["longer"]["methods"]) == rows
    assert len(built) == 1  # the solver was built for the default only
    assert Generalisation("unused").references == HALF_GRID


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
    # backwards on `longer` only (the default inverse_conditions), the forward-only methods named
    inverse = section["conditions"]["longer"]["inverse"]
    assert "inverse" not in section["conditions"]["wide_box"]
    assert set(inverse["without_inverse"]) == {"GNS 8x1", "MPM 32 cells/m"}
    assert set(inverse["methods"]) == {"Const. velocity", "Ballistic + walls"}
    assert inverse["from_frames"] == [11] and inverse["methods"]["Ballistic + walls"]["steps"] == 6
    backwards = markdown_tables((out / "report.md").read_text())[f"Backwards in time on {generated.name}"]
    assert backwards["Method"] == ["longer"] and backwards["GNS 8x1"] == ["no inverse"]
    row = inverse["methods"]["Ballistic + walls"]
    assert backwards["Ballistic + walls"][0].startswith(f"{row['rollout_mse'] * 1e3:.4g} / {row['stable_steps']}")
    pictures = [r.get("break_picture") for c in section["conditions"].values() for r in (c, c.get("inverse") or {})]
    for picture in filter(None, pictures):
        assert (out / picture).stat().st_size > 0 and f"]({picture})" in (out / "report.md").read_text()


class _Factory:
    """tmp_path_factory's mktemp over one test's tmp_path."""

    def __init__(self, root):
        self.root = root

    def mktemp(self, name):
        path = self.root / name
        path.mkdir()
        return path


# --- backwards in time -------------------------------------------------------------------------

METADATA = dict(dim=2, bounds=BOUNDS.tolist(), default_connectivity_radius=RADIUS, vel_mean=[0.0, 0.0],
                vel_std=[1e-3, 1e-3], acc_mean=[0.0, 0.0], acc_std=[1e-4, 1e-4], gravity=[0.0, -9.81])
HISTORY = 5


class Planted(ConstantVelocity):
    """Constant velocity backwards (exact on a drifting lattice) for its first ``at`` inverse steps,
    then its predicted oldest velocity is ``plant(velocity, position, n)`` at the n-th step after
    (0, 1, ..). A velocity predicted at inverse step c (0-based) moves the positions from step
    c + k on: it enters the history as its oldest of k."""

    def __init__(self, metadata: dict, plant, at: int):
        super().__init__(metadata, HISTORY)
        self.plant, self.at, self.calls = plant, at, 0

    def oldest_velocity(self, position, velocity_history, *args, **kwargs):
        velocity = super().oldest_velocity(position, velocity_history, *args, **kwargs)
        self.calls += 1
        return velocity if self.calls <= self.at else self.plant(velocity, position, self.calls - self.at - 1)


def _nan(velocity, position, n):
    return torch.full_like(velocity, float("nan"))


def _one_runs_off(velocity, position, n):
    velocity = velocity.clone()
    velocity[0] = 0.0
    velocity[0, 0] = 0.05  # back in time p^{t-1} = p^t - v: particle 0 runs off to the left
    return velocity


def _jitter(velocity, position, n):
    return torch.full_like(velocity, 0.1 * (-1) ** n)  # back and forth along the diagonal, in the box


def _contract(velocity, position, n):
    return 0.02 * (position - position.mean(0))  # back in time: 2 % nearer the centre each step


def _rest(velocity, position, n):
    return torch.zeros_like(velocity)


def lattice_dataset(frames: int = 81, speed: float = 2e-3, dim: int = 2) -> Dataset:
    truth = drifting(frames, speed=speed)
    metadata = dict(METADATA)
    if dim == 3:  # the same lattice, a layer at z = 0.5
        truth = torch.cat([truth, torch.full((*truth.shape[:2], 1), 0.5)], -1)
        metadata.update(dim=3, bounds=[[0.0, 1.0]] * 3, vel_mean=[0.0] * 3, vel_std=[1e-3] * 3, acc_mean=[0.0] * 3,
                        acc_std=[1e-4] * 3, gravity=[0.0, -9.81, 0.0])
    return Dataset("lattice", "in memory", metadata, [(truth, torch.full((truth.shape[1],), WATER))], start=HISTORY)


def inverse_break(plant, at: int, steps: int = 60, dataset: Dataset | None = None):
    dataset = dataset or lattice_dataset()
    task = Generalisation("unused", steps=steps)
    method = Method("planted", Planted(dataset.metadata, plant, at), None, "baseline")
    section, _, breaks = task.run([method], dataset, "inverse")
    return section["methods"]["planted"], breaks


@pytest.mark.parametrize("stride", [1, 3])
def test_the_inverse_rollout_of_an_exact_inverse_is_the_truth_backwards(stride):
    """Constant velocity is exact backwards on a drifting lattice, at any stride (a model trained
    on every third frame steps back three frames at a time, the frames between filled in)."""
    dataset = lattice_dataset()
    position, particle_type = dataset.trajectories[0]
    model = Planted(dataset.metadata, _rest, at=10**6)  # constant velocity, never planted: counts its steps
    method = Method("exact", model, None, "baseline", trained_metadata={"stride": stride})
    inferred = inverse_rollout(method, position, particle_type, end=80, steps=70)
    assert torch.allclose(inferred, position[10:80].flip(0), atol=1e-5)  # frames 79, 78, .., 10
    assert model.calls == -(-70 // stride)  # steps of `stride` frames


def test_an_exact_inverse_never_breaks():
    row, breaks = inverse_break(_rest, at=10**6)  # never planted
    assert row["first_break"] is None and row["stable_steps"] == 60 and breaks == {}


# planted at inverse step 20 (5 for the slow contraction), the positions change from step 25 (10) on;
# the lattice drifts right at 2e-3 a frame, so backwards particle 0 is at x = 0.2 + 2e-3 (79 - s) at step s
@pytest.mark.parametrize("plant, at, cause, steps", [
    (_nan, 20, "non-finite", (25, 25)),  # the first frame the NaN velocity reaches
    (_one_runs_off, 20, "left the box", (33, 33)),  # x = 0.31 at step 24, then 0.05 a step left: < -0.1 at 24 + 9
    (_jitter, 20, "exploded", (25, 25)),  # energy 2e-2 a step, 5,000x the truth's 4e-6
    (_contract, 5, "compressed", (11, 59)),  # while it contracts (checked against the cells below)
    (_rest, 20, "stalled", (24, 24)),  # the first window of 20 steps with one moving (0.05 of the truth's speed)
])
def test_a_planted_failure_backwards_is_named_at_its_step(plant, at, cause, steps):
    row, breaks = inverse_break(plant, at)
    assert row["first_break"]["cause"] == cause, row["first_break"]
    step = row["first_break"]["step"]
    assert steps[0] <= step <= steps[1]
    if cause == "compressed":
        inferred = torch.as_tensor(breaks["planted"]["predicted"])
        truth = lattice_dataset().trajectories[0][0]
        densest_truth = int(densest_cells(truth, BOUNDS[:, 0], RADIUS).max())
        assert densest_cells(inferred[None], BOUNDS[:, 0], RADIUS)[0] > 3 * densest_truth
    assert row["stable_steps"] == row["first_break"]["step"] and row["steps"] == 60
    broke = breaks["planted"]
    assert broke["frame"] == 80 - 1 - broke["step"] and broke["cause"] == cause  # step s is frame end - 1 - s
    truth = lattice_dataset().trajectories[0][0]
    assert np.allclose(broke["truth"], truth[broke["frame"]].numpy())


def test_methods_without_an_inverse_are_listed_with_the_reason():
    dataset = lattice_dataset()

    class ForwardOnly(ConstantVelocity):
        bidirectional = False

    class Solver:  # a solver reference: no model, forward only
        label, model, bidirectional = "MPM 32 cells/m", None, False

    methods = [Method("forward only", ForwardOnly(dataset.metadata, HISTORY), None, "baseline"), Solver(),
               Method("Const. velocity", ConstantVelocity(dataset.metadata, HISTORY), None, "baseline")]
    section, _, _ = Generalisation("unused", steps=30).run(methods, dataset, "inverse")
    assert set(section["methods"]) == {"Const. velocity"}
    assert section["without_inverse"] == {"forward only": "ForwardOnly simulates forward in time only",
                                          "MPM 32 cells/m": "the dataset's solver runs forward in time only"}
    assert section["from_frames"] == [80]
    from rgns.evaluation.report import generalise_inverse_table
    lines = generalise_inverse_table("lattice", dict(steps=30), {"longer": section})
    rows = {line.split("|")[1].strip(): line.split("|")[2].strip() for line in "\n".join(lines).splitlines()
            if line.startswith("| ")}
    assert rows["forward only"] == rows["MPM 32 cells/m"] == "no inverse"
    assert rows["Const. velocity"].startswith(f"{section['methods']['Const. velocity']['rollout_mse'] * 1e3:.4g} / 30")


@pytest.mark.parametrize("dim, broken, columns", [(2, 4, 6), (3, 2, 4)])
def test_the_break_picture_is_written_in_panels_a_person_can_read(tmp_path, dim, broken, columns):
    """Planted breaks of ``broken`` methods: a PNG of a pair (method, truth) per view, at most six
    panels a row: 2D three methods a row, 3D one a row in two views."""
    import imageio.v2 as imageio

    dataset = lattice_dataset(dim=dim)
    methods = [Method(f"planted {i}", Planted(dataset.metadata, _nan, 10 + i), None, "baseline") for i in range(broken)]
    section, _, breaks = Generalisation("unused", steps=40).run(methods, dataset, "inverse")
    assert set(breaks) == {m.label for m in methods}
    path = tmp_path / "breaks.png"
    assert break_picture(breaks, dataset.bounds, up_axis(dataset.metadata), "planted", path)
    height, width = imageio.imread(path).shape[:2]
    assert width == pytest.approx(2.3 * columns * 110, abs=2)  # the figure's inches at the project's 110 dpi
    rows = broken // (columns // (2 * (dim - 1)))
    assert height > 2.3 * rows * 110
    assert not break_picture({}, dataset.bounds, 1, "nothing broke", tmp_path / "none.png")
    assert not (tmp_path / "none.png").exists()


def test_particle_spans_read_with_thousands_separators():
    from rgns.evaluation.report import span
    assert span([1287, 1053, 1100]) == "1,053-1,287"
    assert span([437, 437]) == "437"
