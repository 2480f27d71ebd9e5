"""The evaluation's yardsticks: the ballistic baseline (gravity and walls) and the dataset's own
solver re-run (coarser grids, the predictability floor), alone and in ``evaluate.py``'s report."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import make_metadata
from hydra import compose, initialize_config_dir

import rgns.evaluation.run as run_module
from rgns.data.contract import KINEMATIC, WATER
from rgns.data.generate import generate_dataset, scene_config
from rgns.data.subset import make_subset
from rgns.evaluation.baselines import Ballistic, Segments, dataset_obstacle_radius
from rgns.evaluation.methods import Method
from rgns.evaluation.references import SolverReferences, grid_substeps, metres
from rgns.evaluation.run import evaluate
from rgns.evaluation.tasks import Dataset
from rgns.models import GNS, State
from rgns.training.rollouts import inverse_then_forward

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 14
HISTORY = 5


def tiny(name: str, tmp_path_factory, frames: int = FRAMES, test: int = 2) -> Path:
    cfg = scene_config(name)
    cfg["splits"] = {"train": 1, "valid": 1, "test": test}
    return generate_dataset(cfg, tmp_path_factory.mktemp(name) / name, num_frames=frames, seed=3, workers=1,
                            progress=False)


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> Path:
    """A generated (MLS-MPM, 64 cells/m, 10 substeps) dataset: 2 test trajectories of 14 frames."""
    return tiny("waterdrop", tmp_path_factory)


def load(root, trajectories=None) -> Dataset:
    return Dataset.load(str(root), "test", trajectories, HISTORY, None)


def mse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).pow(2).mean())


# ---- the ballistic baseline -------------------------------------------------------------------

def ballistic(**changes) -> Ballistic:
    return Ballistic({**make_metadata(), "gravity": [0.0, -9.81], **changes})  # box [0.1, 0.9]^2, dt 0.0025


def at_rest(position) -> State:
    position = torch.tensor(position, dtype=torch.float32)
    return State(position, torch.zeros(len(position), HISTORY, 2), torch.full((len(position),), WATER))


def test_ballistic_adds_gravity_in_free_flight_and_reverses_it():
    model = ballistic()
    g = -9.81 * 0.0025**2  # per frame^2
    assert model.gravity.tolist() == pytest.approx([0.0, g])
    state = at_rest([[0.5, 0.5], [0.3, 0.7]])
    positions = model.rollout(state, 20)
    n = torch.arange(1, 21, dtype=torch.float32)
    expected_drop = g * n * (n + 1) / 2  # v^n = n g, p^n = p^0 + g n (n + 1) / 2
    torch.testing.assert_close(positions[:, :, 1] - state.position[:, 1], expected_drop[:, None].expand(20, 2),
                               atol=1e-6, rtol=0)
    assert (positions[:, :, 0] == state.position[:, 0]).all()  # no horizontal force
    # backwards, the mirror image: K inverse steps recover the start, K forward steps the end
    truth = torch.cat([state.position[None], positions])  # [21, N, D]
    inferred, resimulated = inverse_then_forward(model, truth, state.particle_type, start=HISTORY, steps=10)
    torch.testing.assert_close(inferred[-1], truth[HISTORY], atol=1e-6, rtol=0)
    torch.testing.assert_close(resimulated, truth[HISTORY + 1: HISTORY + 11], atol=1e-6, rtol=0)


def test_ballistic_keeps_particles_in_the_box_and_a_resting_particle_on_the_floor():
    model = ballistic()
    # one thrown at the right wall, one falling onto the floor, one resting on the floor
    position = torch.tensor([[0.88, 0.5], [0.5, 0.102], [0.3, 0.1]])
    velocity = torch.tensor([[0.01, 0.002], [0.0, -0.004], [0.0, 0.0]])
    state = State(position, velocity[:, None].expand(-1, HISTORY, -1).contiguous(), torch.full((3,), WATER))
    positions = model.rollout(state, 50)
    assert (positions >= 0.1).all() and (positions <= 0.9).all()
    assert positions[-1, 0, 0] == pytest.approx(0.9)  # against the wall ...
    assert (positions[3:, 0, 0] == positions[3, 0, 0]).all()  # ... its velocity into the wall zeroed
    assert (positions[:, 2] == position[2]).all()  # at rest on the floor, every step
    assert (positions[5:, 1, 1] == np.float32(0.1)).all()  # the falling one lands and stays
    # backwards, the resting particle stays on the floor too
    resting = at_rest([[0.3, 0.1]])
    assert (model.inverse_rollout(resting, 10) == resting.position).all()


def test_ballistic_without_gravity_in_the_metadata_uses_the_mean_acceleration():
    metadata = {**make_metadata(), "acc_mean": [1e-7, -5e-5]}
    assert "gravity" not in metadata  # as in DeepMind's metadata.json
    assert Ballistic(metadata).gravity.tolist() == pytest.approx([1e-7, -5e-5])


def ramp_state(position, ramp_from, ramp_to, spacing=0.0065, kinematic=True) -> State:
    """Water particles at rest at ``position`` and a ramp of particles ``spacing`` apart from ``ramp_from`` to ``ramp_to``."""
    a, b = np.asarray(ramp_from), np.asarray(ramp_to)
    count = int(np.ceil(np.linalg.norm(b - a) / spacing)) + 1
    ramp = a + np.linspace(0.0, 1.0, count)[:, None] * (b - a)
    points = torch.tensor(np.concatenate([np.asarray(position), ramp]), dtype=torch.float32)
    types = torch.cat([torch.full((len(position),), WATER), torch.full((count,), KINEMATIC if kinematic else WATER)])
    return State(points, torch.zeros(len(points), HISTORY, 2), types)


def test_ballistic_lands_on_a_ramp_and_stays_there():
    model = ballistic(generator={"params": {"ramp_radius": 0.0065}})
    assert model.obstacle_radius == 0.0065
    # one above a level ramp, one beside it; the ramp's particles stay where they are (kinematic)
    state = ramp_state([[0.5, 0.55], [0.8, 0.55]], [0.4, 0.5], [0.6, 0.5])
    positions = model.rollout(state, 150)
    assert positions[-1, 1, 1] == pytest.approx(0.1)  # beside the ramp: on the floor
    height = positions[:, 0, 1] - 0.5
    assert height.min() == pytest.approx(0.0065, abs=1e-6)  # on the ramp, its half thickness above the axis
    assert height[-50:].tolist() == pytest.approx([0.0065] * 50, abs=1e-7)  # at rest there
    assert positions[-50:, 0, 0].tolist() == pytest.approx([0.5] * 50, abs=1e-7)
    # backwards from rest on the ramp: it stays (the floor's mirror image)
    resting = ramp_state([[0.5, 0.5065]], [0.4, 0.5], [0.6, 0.5])
    assert (model.inverse_rollout(resting, 10)[:, 0] == resting.position[0]).all()
    # without kinematic particles the same start falls through to the floor
    through = model.rollout(ramp_state([[0.5, 0.55]], [0.4, 0.5], [0.6, 0.5], kinematic=False), 150)
    assert through[-1, 0, 1] == pytest.approx(0.1)


def test_ballistic_slides_down_a_sloped_ramp_without_entering_it():
    model = ballistic(generator={"params": {"ramp_radius": 0.0065}})
    state = ramp_state([[0.5, 0.56]], [0.3, 0.6], [0.7, 0.4])  # slope 0.5, falling to the right
    positions = model.rollout(state, 80)
    a, b = torch.tensor([0.3, 0.6]), torch.tensor([0.7, 0.4])
    along = ((positions[:, 0] - a) @ (b - a)) / (b - a).dot(b - a)
    foot = a + along[:, None] * (b - a)
    distance = (positions[:, 0] - foot).norm(dim=-1)
    assert distance.min() >= 0.0065 - 1e-5  # never inside the ramp
    assert positions[-1, 0, 0] > 0.52 and bool((torch.diff(along[20:]) > 0).all())  # sliding down the slope


def test_ballistic_leaves_a_particle_inside_a_ramps_margin_where_it_is():
    model = ballistic(generator={"params": {"ramp_radius": 0.0065}})
    state = ramp_state([[0.5, 0.503]], [0.4, 0.5], [0.6, 0.5])  # 3 mm above the axis: inside the margin
    assert (model.rollout(state, 20)[:, 0] == state.position[0]).all()  # not pushed out, not let further in


def test_obstacle_segments_stay_within_their_graph_of_a_batch():
    # graph 0: a ramp of three particles and one water particle above it; graph 1: one lone kinematic
    # particle far away, one water particle above graph 0's ramp (another scene: it must fall through);
    # graph 2: another lone kinematic particle (two lone ones are never linked across graphs)
    position = torch.tensor([[0.5, 0.5], [0.5065, 0.5], [0.513, 0.5], [0.5, 0.51],
                             [0.2, 0.2], [0.5065, 0.51], [0.8, 0.8]])
    types = torch.tensor([KINEMATIC, KINEMATIC, KINEMATIC, WATER, KINEMATIC, WATER, KINEMATIC])
    batch = torch.tensor([0, 0, 0, 0, 1, 1, 2])
    segments = Segments.of(position, types, batch)
    links = {(tuple(a.tolist()), tuple(b.tolist())) for a, b, g in zip(segments.a, segments.b, segments.graph)
             if not torch.equal(a, b)}
    assert len(links) == 2 and all(g == 0 for a, b, g in zip(segments.a, segments.b, segments.graph) if not torch.equal(a, b))
    end = position[[3, 5]] - torch.tensor([0.0, 0.01])  # both move 1 cm down, onto graph 0's ramp axis
    kept = Segments(segments.a, segments.b, segments.graph, batch[[3, 5]]).keep_out(position[[3, 5]], end, 0.0065)
    assert kept[0].tolist() == pytest.approx([0.5, 0.5065])  # held on its own graph's ramp
    assert torch.equal(kept[1], end[1])  # graph 1 has no ramp there: it passes


def test_obstacle_radius_comes_from_the_scene_or_the_connectivity_radius():
    assert dataset_obstacle_radius({"default_connectivity_radius": 0.015}) == pytest.approx(0.0075)
    assert dataset_obstacle_radius({"default_connectivity_radius": 0.015,
                                    "generator": {"params": {"ramp_radius": 0.004}}}) == 0.004
    assert Ballistic({**make_metadata(), "gravity": [0.0, -9.81]}, obstacle_radius=0.002).obstacle_radius == 0.002


# ---- the solver re-run ------------------------------------------------------------------------

def test_full_resolution_rerun_reproduces_the_stored_trajectories(generated):
    dataset = load(generated)
    (exact,), note = SolverReferences(resolutions=[1.0], floor_perturbation=None)(dataset)
    assert note is None and exact.label == "MPM 64 cells/m" and exact.settings["substeps"] == 10
    for i, (position, _) in enumerate(dataset.trajectories):
        torch.testing.assert_close(exact.trajectory(dataset, i, len(position)), position, atol=0, rtol=0)
    # the window compared is the learned models': frames t0+1 .. t0+steps, t0 = k
    window = exact.forward_rollout(dataset, 1, 4)
    assert (window == dataset.trajectories[1][0][HISTORY + 1: HISTORY + 5]).all()


def test_rerun_with_ramps_keeps_the_stored_obstacles(tmp_path_factory):
    ramps = tiny("waterramps", tmp_path_factory, frames=8, test=1)
    dataset = load(ramps)
    position, particle_type = dataset.trajectories[0]
    assert (particle_type == KINEMATIC).any()
    (exact,), note = SolverReferences(resolutions=[1.0], floor_perturbation=None)(dataset)
    assert note is None
    torch.testing.assert_close(exact.trajectory(dataset, 0, len(position)), position, atol=0, rtol=0)


def test_coarser_grids_take_substeps_in_proportion_and_the_floor_starts_perturbed(generated, record_property):
    assert [grid_substeps(n, 64, 10) for n in (32, 48, 64, 1)] == [5, 8, 10, 1]
    (single,), _ = SolverReferences(resolutions=[0.5, 0.5], floor_perturbation=None)(load(generated))
    assert single.label == "MPM 32 cells/m"  # one row per grid
    assert grid_substeps(16, 64, 3) == 1 and metres(1e-4) == "1e-4" and metres(2.5e-5) == "2.5e-5"
    dataset = load(generated)
    references, note = SolverReferences()(dataset)  # the defaults of conf/evaluate.yaml
    assert note is None
    assert [r.label for r in references] == ["MPM 32 cells/m", "MPM 48 cells/m", "MPM floor (1e-4 m)"]
    assert [(r.scene.solver.n_grid, r.scene.solver.substeps) for r in references] == [(32, 5), (48, 8), (64, 10)]
    cells = [r.scene.solver.dx for r in references]  # ~1 / n_grid, so that the box spans whole cells
    assert cells[0] > cells[1] > cells[2] and cells[0] == pytest.approx(1 / 32, rel=0.05)
    coarse, _, floor = references
    position = dataset.trajectories[0][0]
    coarse_run, floor_run = (r.trajectory(dataset, 0, len(position)) for r in (coarse, floor))
    assert (coarse_run[0] == position[0]).all() and mse(coarse_run[-1], position[-1]) > 0  # same start, other path
    assert mse(floor_run[0], position[0]) == pytest.approx(1e-8, rel=0.3)  # noise of std 1e-4 m at frame 0
    # measured, not asserted (timings are not tested): the coarse grid's cost per frame against the stored one's
    ratio = coarse.ms_per_frame(0) / floor.ms_per_frame(0)
    record_property("ms_per_frame_32_over_64", ratio)
    print(f"ms per frame: 32 cells/m {coarse.ms_per_frame(0):.3g}, 64 cells/m {floor.ms_per_frame(0):.3g}, "
          f"ratio {ratio:.2f}")


def test_sph_dataset_gets_coarser_time_steps_and_the_floor(tmp_path_factory):
    sph = tiny("dambreak_sph", tmp_path_factory, frames=4, test=1)
    dataset = load(sph)
    references, note = SolverReferences()(dataset)  # 25 substeps stored: 0.5 -> 13, 0.75 -> 19
    assert [r.label for r in references] == ["SPH 13 substeps", "SPH 19 substeps", "SPH floor (1e-4 m)"]
    assert note is None
    coarse = references[0].settings
    assert (coarse["substeps"], coarse["sound_speed"], coarse["viscosity"]) == pytest.approx((13, 13.0, 0.05 * 25 / 13))
    run = references[-1].trajectory(dataset, 0, 3)  # the floor
    assert run.shape == dataset.trajectories[0][0][:3].shape and 0 < mse(run, dataset.trajectories[0][0][:3]) < 1e-7



@pytest.fixture(scope="module")
def water3d(tmp_path_factory) -> Path:
    """A tiny ``water3d`` (WCSPH in 3D, 20 substeps, c = 25 m/s): 30-120 particles, 14 frames."""
    cfg = scene_config("water3d")
    cfg.update(splits={"train": 1, "valid": 1, "test": 1}, particles=[30, 120], body_size=[0.06, 0.1])
    return generate_dataset(cfg, tmp_path_factory.mktemp("water3d") / "water3d", num_frames=FRAMES, seed=3,
                            workers=1, progress=False)


def test_water3d_rerun_at_the_stored_substeps_reproduces_it_and_coarser_ones_keep_cfl_and_viscosity(water3d):
    dataset = load(water3d)
    position = dataset.trajectories[0][0]
    assert position.shape[-1] == 3
    (exact,), note = SolverReferences(resolutions=[1.0], floor_perturbation=None)(dataset)
    assert note is None and exact.label == "SPH 20 substeps"
    assert exact.settings["sound_speed"] == 25.0 and exact.settings["viscosity"] == 0.05
    torch.testing.assert_close(exact.trajectory(dataset, 0, len(position)), position, atol=0, rtol=0)
    references, note = SolverReferences()(dataset)  # the defaults of conf/evaluate.yaml
    assert note is None
    assert [r.label for r in references] == ["SPH 10 substeps", "SPH 15 substeps", "SPH floor (1e-4 m)"]
    for reference in references[:2]:
        solver = reference.scene.solver
        assert solver.dt * solver.sound_speed == pytest.approx(0.005 / 20 * 25.0)  # the CFL number as stored
        assert solver.alpha * solver.sound_speed == pytest.approx(0.05 * 25.0)  # the modelled viscosity as stored
        assert solver.spacing == 0.022 and solver.h == exact.scene.solver.h  # the same particles and kernel


def test_water3d_dataset_gets_every_yardstick(water3d, tmp_path, monkeypatch):
    """evaluate.py on a 3D SPH dataset: constant velocity, ballistic with walls, the solver coarser
    in time and the predictability floor, beside a stand-in for a trained checkpoint."""
    cfg = stand_in_config(water3d, monkeypatch, ["task=forward", f"output_dir={tmp_path}", "trajectories=1",
                                                 "task.forward.distribution_steps=[1]", "task.efficiency.repeats=1",
                                                 "task.efficiency.memory=false", "animation.max_frames=3"])
    data = evaluate(cfg)["datasets"][water3d.name]
    solvers = ["SPH 10 substeps", "SPH 15 substeps", "SPH floor (1e-4 m)"]
    forward, cost = data["forward"]["methods"], data["efficiency"]["methods"]
    assert list(forward) == ["GNS 8x1", "Const. velocity", "Ballistic + walls", *solvers]
    assert list(data["references"]["methods"]) == solvers and data["references"]["note"] is None
    for label in forward:
        assert np.isfinite(forward[label]["rollout_mse"]) and forward[label]["rollout_mse"] > 0, label
    for label in solvers:
        assert cost[label]["forward_ms_per_step"] > 0 and cost[label]["parameters"] == 0
        assert data["references"]["methods"][label]["frames_per_trajectory"] == {"0": FRAMES - 1}
    assert forward["Ballistic + walls"]["rollout_mse"] < forward["Const. velocity"]["rollout_mse"]  # gravity along -y
    # a ladder: the coarser in time, the further from the stored run; all closer to it than the baselines
    assert forward["SPH 10 substeps"]["rollout_mse"] > forward["SPH 15 substeps"]["rollout_mse"]
    assert forward["SPH 10 substeps"]["rollout_mse"] < forward["Ballistic + walls"]["rollout_mse"]
    report = (tmp_path / "report.md").read_text()
    assert "SPH 10 substeps: the dataset's solver (rgns.physics.sph.SPHSolver) re-run from the same initial " \
           "states with 10 substeps per frame, sound speed 12.5 m/s and viscosity alpha 0.1" in report

def test_datasets_without_a_rebuildable_generator_get_no_solver_and_say_why(generated):
    converted = Dataset("converted", "", make_metadata(), load(generated).trajectories, start=HISTORY)
    references, note = SolverReferences()(converted)
    assert references == [] and note.startswith("No solver references: the metadata records no generator")
    metadata = copy.deepcopy(load(generated).metadata)
    metadata["generator"]["params"]["_target_"] = "rgns.data.scenes.NoSuchScene"
    references, note = SolverReferences()(Dataset("broken", "", metadata, converted.trajectories, start=HISTORY))
    assert references == [] and "cannot be rebuilt" in note
    metadata = copy.deepcopy(load(generated).metadata)
    metadata["generator"]["seed"] += 1  # other initial states than the stored ones
    references, note = SolverReferences()(Dataset("changed", "", metadata, converted.trajectories, start=HISTORY))
    assert references == [] and "is not the stored one" in note


def test_a_subset_of_a_split_reruns_from_its_own_initial_states(generated, tmp_path):
    # trajectory 1 alone, renumbered 0: the solver must redraw draw 1, which the subset records
    subset = make_subset(generated, tmp_path / "second", "test", "1")
    dataset = load(subset)
    (exact,), note = SolverReferences(resolutions=[1.0], floor_perturbation=None)(dataset)
    assert note is None
    position = dataset.trajectories[0][0]
    assert (position == load(generated).trajectories[1][0]).all()
    torch.testing.assert_close(exact.trajectory(dataset, 0, len(position)), position, atol=0, rtol=0)
    # without the record the redraw is trajectory 0's, and the reference says so instead of comparing
    metadata = copy.deepcopy(dataset.metadata)
    del metadata["generator"]["draws"]
    references, note = SolverReferences()(Dataset("renumbered", "", metadata, dataset.trajectories, start=HISTORY))
    assert references == [] and "is not the stored one" in note


# ---- in evaluate.py's results and report ------------------------------------------------------

def stand_in_config(generated, monkeypatch, overrides: list[str]):
    """The evaluate config for ``overrides``, with an untrained GNS standing in for a checkpoint."""
    metadata = json.loads((generated / "metadata.json").read_text())
    stand_in = Method("GNS 8x1", GNS(metadata, latent=8, layers=1).eval(), str(generated), "stand-in.ckpt")
    monkeypatch.setattr(run_module, "find_checkpoints", lambda *args, **_: [])
    monkeypatch.setattr(run_module, "load_checkpoints", lambda paths, device, **_: [stand_in])
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("evaluate", overrides=overrides)


def test_report_and_results_carry_the_reference_rows(generated, tmp_path, monkeypatch):
    """A stand-in for a trained checkpoint (an untrained GNS) beside the baselines and references."""
    from test_evaluate import markdown_tables, value

    cfg = stand_in_config(generated, monkeypatch, ["task=forward", f"output_dir={tmp_path}", "trajectories=2",
                                                   "task.forward.distribution_steps=[1]", "task.efficiency.repeats=1",
                                                   "task.efficiency.memory=false", "animation.max_frames=3"])
    evaluate(cfg)
    results = json.loads((tmp_path / "results.json").read_text())
    data = results["datasets"][generated.name]
    solvers = ["MPM 32 cells/m", "MPM 48 cells/m", "MPM floor (1e-4 m)"]
    assert list(data["forward"]["methods"]) == ["GNS 8x1", "Const. velocity", "Ballistic + walls", *solvers]
    assert list(data["references"]["methods"]) == solvers and data["references"]["note"] is None
    forward, cost, summary = data["forward"]["methods"], data["efficiency"]["methods"], data["summary"]
    for label in solvers:
        assert results["methods"][label]["source"] == "reference"
        assert forward[label]["rollout_mse"] > 0 and cost[label]["forward_ms_per_step"] > 0 and cost[label]["parameters"] == 0
        assert summary[label]["forward_ms_per_step"] == cost[label]["forward_ms_per_step"]
        assert label not in data.get("inverse", {}).get("methods", {})
        runs = data["references"]["methods"][label]
        assert runs["frames_per_trajectory"] == {"0": FRAMES - 1, "1": FRAMES - 1}  # from frame 0 to the window's end
    assert data["references"]["methods"]["MPM 32 cells/m"]["substeps"] == 5
    assert forward["Ballistic + walls"]["rollout_mse"] < forward["Const. velocity"]["rollout_mse"]  # it knows gravity

    report = (tmp_path / "report.md").read_text()
    tables = markdown_tables(report)
    rollout = tables["Rollout MSE (1e-3) in the forward process"]
    header = rollout["Dataset / Methods"]
    assert header == list(forward)
    for label, cell in zip(header, rollout[generated.name]):
        assert value(cell) == pytest.approx(forward[label]["rollout_mse"] * 1e3, rel=1e-3)
        assert not (label in solvers and "**" in cell)  # a yardstick is never the bold best
    times = tables[f"Efficiency comparison on {generated.name}"]
    for label, cell in zip(times["Metrics / Methods"], times["Forward Inference Time (ms/step)"]):
        assert value(cell) == pytest.approx(cost[label]["forward_ms_per_step"], rel=1e-3)
    assert "MPM 32 cells/m: the dataset's solver (rgns.physics.mpm.MPMSolver) re-run from the same initial " \
           "states at 32 cells/m with 5 substeps per frame" in report
    assert "MPM floor (1e-4 m): the predictability floor" in report and "JIT warm-up excluded" in report
    assert (tmp_path / "accuracy_vs_speed.png").stat().st_size > 0


def test_references_null_drops_them(generated, tmp_path, monkeypatch):
    cfg = stand_in_config(generated, monkeypatch, ["task=forward", f"output_dir={tmp_path}", "references=null",
                                                   "baselines=null", "task.efficiency=null", "task.forward.steps=2",
                                                   "task.forward.distribution_steps=[1]", "animation.max_frames=2"])
    results = evaluate(cfg)
    data = results["datasets"][generated.name]
    assert list(data["forward"]["methods"]) == ["GNS 8x1"] and "references" not in data
    assert "Solver references" not in (tmp_path / "report.md").read_text()


def test_precision_and_neighbour_skin_reach_every_checkpoint_and_a_bad_precision_is_refused(generated, tmp_path,
                                                                                           monkeypatch):
    from rgns.errors import ConfigError

    overrides = ["task=forward", "references=null", "baselines=null", "task.efficiency=null", "task.forward.steps=3",
                 "task.forward.distribution_steps=[1]", "animation.max_frames=2", "trajectories=1"]
    scores = {}
    for precision in ("float32", "bfloat16"):
        cfg = stand_in_config(generated, monkeypatch, [*overrides, f"output_dir={tmp_path / precision}",
                                                       f"precision={precision}", "neighbour_skin=0.2"])
        stand_in = run_module.load_checkpoints([], "cpu")[0]
        scores[precision] = evaluate(cfg)["datasets"][generated.name]["forward"]["methods"]["GNS 8x1"]["rollout_mse"]
        assert stand_in.model.precision == precision and stand_in.model.neighbour_skin == 0.2
    assert scores["bfloat16"] != scores["float32"]  # the other arithmetic was used
    cfg = stand_in_config(generated, monkeypatch, [*overrides, f"output_dir={tmp_path / 'half'}", "precision=float16"])
    with pytest.raises(ConfigError, match="precision='float16'"):
        evaluate(cfg)
