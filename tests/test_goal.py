"""Goal-conditioned shaping: shapes render to the expected particles and are placed where asked,
with the velocity history asked for; the physics check (the dataset's own solver) returns a known
answer; the plausibility checks flag planted faults; the task runs in 2D and 3D."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from scipy.spatial import cKDTree

from rgns.data.scenes import lattice
from rgns.evaluation.metrics import chamfer
from rgns.inverse.goal import (GoalSpec, GroundTruthSolver, extrude, mask_to_points, plausibility, render_text,
                               run_goal, target_points, target_state)
from rgns.inverse.simulators import dataset_spacing
from rgns.models import RGNS, State

SPACING = 0.0065
CONF = Path(__file__).resolve().parents[1] / "conf" / "scene"

METADATA = dict(bounds=[[0.1, 0.9], [0.1, 0.9]], dim=2, default_connectivity_radius=0.015, dt=0.0025,
                vel_mean=[0.0, 0.0], vel_std=[1.3e-3, 1.3e-3], acc_mean=[0.0, 0.0], acc_std=[1e-4, 1e-4],
                generator=dict(params=dict(spacing=SPACING)))


@pytest.fixture(autouse=True)
def one_thread():
    torch.set_num_threads(1)
    torch.manual_seed(0)


def generated_metadata(scene: str) -> dict:
    """The metadata of a dataset generated from ``conf/scene/<scene>.yaml``: its box, frame time,
    gravity, and the generator's parameters (what the physics check rebuilds the solver from)."""
    params = OmegaConf.to_container(OmegaConf.load(CONF / f"{scene}.yaml"))
    dim = params["dim"]
    return dict(bounds=params["bounds"], dim=dim, default_connectivity_radius=params["connectivity_radius"],
                dt=params["dt"], gravity=params["gravity"], vel_mean=[0.0] * dim, vel_std=[1.3e-3] * dim,
                acc_mean=[0.0] * dim, acc_std=[1e-4] * dim, generator=dict(params=params, seed=0))


class Recorder:
    """A bidirectional stand-in that records the state its first inverse step gets and stays put."""

    bidirectional, history = True, 5

    def __init__(self):
        self.seen: list[State] = []

    def inverse_step(self, state: State) -> State:
        self.seen.append(state)
        return state

    def rollout(self, state: State, steps: int) -> torch.Tensor:
        return state.position.expand(steps, *state.position.shape).clone()


# ---------------------------------------------------------------------------------------------- shapes
def test_square_mask_gives_expected_count_and_spacing():
    side, h = 20 * SPACING, SPACING
    mask = np.ones((200, 200), bool)
    points = mask_to_points(mask, side / 200, h)
    assert len(points) == round(side / h) ** 2
    distance, _ = cKDTree(points).query(points, k=2)
    assert np.allclose(distance[:, 1], h, rtol=1e-6)


def test_mask_with_a_hole_and_extrusion():
    mask = np.ones((100, 100), bool)
    mask[25:75, 25:75] = False  # a square ring: outer 20 h, hole 10 h
    points = mask_to_points(mask, 20 * SPACING / 100, SPACING)
    assert len(points) == 20**2 - 10**2
    solid = extrude(points, depth=4 * SPACING, spacing=SPACING, centre=0.5)
    assert solid.shape == (4 * len(points), 3)
    assert np.allclose(np.unique(solid[:, 2]) - 0.5, (np.arange(4) - 1.5) * SPACING)


def test_text_renders_to_particles_at_spacing_on_the_floor():
    mask = render_text("L")
    assert mask.any() and mask[:, 0].any() and mask[-1].all()  # cropped to the ink; L's foot is its bottom row
    spec = GoalSpec(text="LN", height=0.2, place="floor")
    points = target_points(spec, METADATA["bounds"], SPACING, dim=2)
    distance, _ = cKDTree(points).query(points, k=2)
    assert np.allclose(distance[:, 1], SPACING, rtol=1e-5)
    assert points[:, 1].min() == pytest.approx(0.1 + SPACING / 2, abs=1e-6)  # standing on the floor
    height = points[:, 1].max() - points[:, 1].min()
    assert 0.2 - 2 * SPACING < height < 0.2  # cell centres inside a 0.2 m glyph
    # the L's stem: a filled column, so its particle count is close to stem area / h^2
    ink = render_text("L").mean()
    expected = ink * render_text("L").shape[1] / render_text("L").shape[0] * 0.2**2 / SPACING**2
    count = len(target_points(GoalSpec(text="L", height=0.2), METADATA["bounds"], SPACING, dim=2))
    assert abs(count - expected) < 0.1 * expected
    three = target_points(GoalSpec(text="L", height=0.2, depth=5 * SPACING), [[0.1, 0.9]] * 3, SPACING, dim=3)
    assert len(three) == 5 * count


def test_points_file_and_spacing_from_metadata_or_frame(tmp_path):
    circle = np.array([[np.cos(a), np.sin(a)] for a in np.linspace(0, 2 * np.pi, 40, endpoint=False)]) * 0.1
    np.save(tmp_path / "circle.npy", circle)
    points = target_points(GoalSpec(points=str(tmp_path / "circle.npy"), place="centre"), METADATA["bounds"], SPACING, 2)
    assert points.shape == (40, 2) and np.allclose(points.mean(0), 0.5, atol=1e-6)
    with pytest.raises(ValueError, match="does not fit"):
        target_points(GoalSpec(points=str(tmp_path / "circle.npy"), place="none"), METADATA["bounds"], SPACING, 2)
    assert dataset_spacing(METADATA) == SPACING
    frame = lattice(np.array([0.2, 0.2]), np.array([0.3, 0.3]), 0.01)
    assert dataset_spacing({}, frame) == pytest.approx(0.01)


# ---------------------------------------------------------------------------------------------- placement and velocity
def test_target_mid_air_at_rest_has_zero_history_and_the_placement_asked_for(tmp_path):
    box = [[0.1, 0.5], [0.1, 0.5]]  # WaterDrop's
    metadata = dict(METADATA, bounds=box)
    spec = GoalSpec(text="LN", height=0.2, place="air", lift=0.1)
    points = target_points(spec, box, SPACING, dim=2)
    assert points[:, 1].min() == pytest.approx(0.1 + 0.1, abs=1e-6)  # its bottom 0.1 m above the floor
    assert 0.5 * (points[:, 0].min() + points[:, 0].max()) == pytest.approx(0.3, abs=1e-6)  # centred in x
    with pytest.raises(ValueError, match="does not fit"):
        target_points(GoalSpec(text="LN", height=0.2, place="air", lift=0.25), box, SPACING, dim=2)

    recorder = Recorder()
    results = run_goal({"recorder": recorder}, metadata, spec, tmp_path, steps=[2], physics=False)
    (seen, *_) = recorder.seen
    assert torch.equal(seen.position, torch.as_tensor(points))
    assert seen.velocity_history.shape == (len(points), 5, 2) and not seen.velocity_history.any()
    assert results["velocity"] == [0.0, 0.0] and results["steps"] == [2]


def test_target_with_a_velocity_gets_it_per_frame_in_every_history_slot(tmp_path):
    """State holds velocities as displacements per frame: v (m/s) x dt in each of the k slots."""
    recorder = Recorder()
    spec = GoalSpec(text="L", height=0.05, place="centre", velocity=[0.4, -1.2])
    run_goal({"recorder": recorder}, METADATA, spec, tmp_path, steps=[1], physics=False)
    history = recorder.seen[0].velocity_history  # [N, k, D]
    expected = torch.tensor([0.4, -1.2]) * METADATA["dt"]  # [1e-3, -3e-3] per frame
    assert torch.allclose(history, expected.expand_as(history), rtol=0, atol=1e-9)
    state = target_state(torch.zeros(3, 3), history=4, velocity=torch.tensor([1.0, 2.0, 3.0]))
    assert state.velocity_history.shape == (3, 4, 3) and (state.velocity_history == torch.tensor([1.0, 2.0, 3.0])).all()
    assert GoalSpec(velocity=[0.5, 1.0]).target_velocity(3).tolist() == [0.5, 1.0, 0.0]  # 3D: no z
    with pytest.raises(ValueError, match="give 2 components"):
        GoalSpec(velocity=[0.5, 1.0, 2.0]).target_velocity(2)


# ---------------------------------------------------------------------------------------------- the physics check
def test_solver_brings_a_ballistic_blob_back_to_its_known_target():
    """A blob at rest density on the lattice, in free flight away from the walls, at rest at frame K
    (the top of its flight). MLS-MPM integrates each of its n = K x substeps substeps as
    ``v += g dt_s; x += v dt_s``, so from ``v0 = v_K - n g dt_s`` the blob reaches
    ``x_n = x0 + n v0 dt_s + g dt_s^2 n (n + 1) / 2``: the exact initial state is known."""
    metadata = generated_metadata("waterdrop")
    K, substeps = 8, metadata["generator"]["params"]["solver"]["substeps"]
    dt_s, n = metadata["dt"] / substeps, K * substeps
    gravity = np.asarray(metadata["gravity"])
    target = lattice(np.array([0.27, 0.32]), np.array([0.27, 0.32]) + 8 * SPACING, SPACING)  # [64, 2]
    v0 = -n * gravity * dt_s  # m/s: upwards, at rest at frame K
    x0 = target - n * v0 * dt_s - gravity * dt_s**2 * n * (n + 1) / 2
    solver, note = GroundTruthSolver.for_dataset(metadata, len(target))
    assert note is None and solver.label == "MPM"
    frames, info = solver.run(x0, np.broadcast_to(v0 * metadata["dt"], x0.shape), K)  # per-frame velocity in
    assert frames.shape == (K + 1, len(target), 2) and info["clamped"] == 0
    exact = chamfer(torch.as_tensor(frames[-1], dtype=torch.float64), torch.as_tensor(target, dtype=torch.float64))
    assert exact < 1e-6 * SPACING**2  # float32 rounding; x0 from the continuous-time formula is off by 1.4e-5
    # doing nothing: the blob at rest falls by about g (K dt)^2 / 2 = 2 mm, a third of a spacing
    still, _ = solver.run(target, np.zeros_like(target), K)
    fallen = chamfer(torch.as_tensor(still[-1], dtype=torch.float64), torch.as_tensor(target, dtype=torch.float64))
    assert fallen > 0.05 * SPACING**2 and fallen > 1e3 * exact
    # a particle outside the box is put on the wall before the solver runs, and that is reported
    outside = target.copy()
    outside[0] = [0.55, 0.3]
    frames, info = solver.run(outside, np.zeros_like(outside), 1)
    assert info["clamped"] == pytest.approx(1 / len(target)) and frames[0, 0, 0] == pytest.approx(0.5)


def test_no_physics_check_without_a_generator():
    solver, note = GroundTruthSolver.for_dataset(dict(METADATA, generator=None), 10)
    assert solver is None and "no generator" in note


def test_plausibility_flags_a_planted_overlap_and_a_particle_outside_the_box():
    bounds = [[0.1, 0.5], [0.1, 0.5]]
    clean = lattice(np.array([0.2, 0.2]), np.array([0.2, 0.2]) + 10 * SPACING, SPACING)  # [100, 2]
    still = np.zeros_like(clean)
    check = plausibility(clean, still, bounds, SPACING, dt=0.0025, max_speed=1.0)
    assert check["flags"] == [] and check["inside_box"] == 1 and check["overlapping"] == 0 == check["isolated"]
    overlap = clean.copy()
    overlap[0] = overlap[1] + [0.2 * SPACING, 0.0]  # on top of its neighbour (and off the lattice corner)
    check = plausibility(overlap, still, bounds, SPACING, dt=0.0025, max_speed=1.0)
    assert check["overlapping"] == pytest.approx(2 / 100) and check["inside_box"] == 1
    assert any("overlapping" in flag for flag in check["flags"]) and not any("outside" in f for f in check["flags"])
    out = clean.copy()
    out[-1] = [0.6, 0.3]  # out of the box (and far from the rest)
    check = plausibility(out, still, bounds, SPACING, dt=0.0025, max_speed=1.0)
    assert check["inside_box"] == pytest.approx(0.99) and check["isolated"] == pytest.approx(0.01)
    assert any("outside the box" in flag for flag in check["flags"]) and check["overlapping"] == 0
    fast = still.copy()
    fast[3] = [0.0, 2.0 * 0.0025]  # 2 m/s, per frame
    check = plausibility(clean, fast, bounds, SPACING, dt=0.0025, max_speed=1.0)
    assert check["max_speed"] == pytest.approx(2.0) and any("max speed" in flag for flag in check["flags"])
    assert check["mean_velocity"] == pytest.approx([0.0, 2.0 / 100])


# ---------------------------------------------------------------------------------------------- the task
def test_run_goal_with_the_physics_check_and_do_nothing_writes_figures_and_metrics(tmp_path):
    metadata = generated_metadata("waterdrop")
    model = RGNS(metadata, latent=16, layers=2)
    spec = GoalSpec(text="L", height=0.05, place="air", lift=0.1)
    results = run_goal({"R-GNS": model}, metadata, spec, tmp_path, steps=[2, 3], max_speed=1.0)
    assert results["physics"]["solver"] == "MPM" and list(results["horizons"]) == ["2", "3"]
    for K, at in results["horizons"].items():
        rgns, still = at["methods"]["R-GNS"], at["methods"]["do nothing"]
        # untrained R-GNS from rest: the inferred initial state is the target, and so is its reproduction
        assert rgns["model"]["chamfer"] < 1e-10 and still["model"] is None and still["status"] == "no planning"
        # the solver from the target at rest: the same fall for both, a little after K frames
        assert rgns["solver"]["chamfer"] == pytest.approx(still["solver"]["chamfer"], rel=1e-3)
        assert still["solver"]["chamfer"] > 0 and still["plausibility"]["flags"] == []
    for name in results["files"]:
        assert (tmp_path / name).stat().st_size > 0
    assert {"goal_L_K2.png", "goal_L_K3.gif", "goal_L.json"} <= set(results["files"])
    assert json.loads((tmp_path / "goal_L.json").read_text())["particles"] == results["particles"]


def test_goal_in_3d_extruded_and_run_by_the_dataset_solver(tmp_path):
    metadata = generated_metadata("water3d")
    spacing = metadata["generator"]["params"]["spacing"]
    model = RGNS(metadata, latent=16, layers=2)
    spec = GoalSpec(text="L", height=0.1, depth=2 * spacing, place="air", lift=0.1, velocity=[0.0, 0.5])
    results = run_goal({"R-GNS": model}, metadata, spec, tmp_path, steps=[2])
    one_layer = target_points(GoalSpec(text="L", height=0.1, depth=spacing), metadata["bounds"], spacing, dim=3)
    assert results["dim"] == 3 and results["particles"] == 2 * len(one_layer)  # extruded: two layers along z
    assert results["velocity"] == [0.0, 0.5, 0.0] and results["physics"]["solver"] == "SPH"
    at = results["horizons"]["2"]["methods"]
    assert at["R-GNS"]["solver"]["chamfer"] is not None and at["do nothing"]["solver"]["chamfer"] is not None
    assert (tmp_path / "goal_L_K2.png").stat().st_size > 0 and (tmp_path / "goal_L_K2.gif").stat().st_size > 0


# ---------------------------------------------------------------------------------------------- 3D views, several texts
def closed_figures(monkeypatch) -> list:
    """Every matplotlib figure closed from now on (the goal figure when it is saved, each frame of
    the animation after it is drawn), recorded before it is closed."""
    import matplotlib.pyplot as plt

    closed, close = [], plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: (closed.append(fig), close(fig))[1])
    return closed


def panel_titles(fig) -> list[str]:
    return [ax.get_title() for ax in fig.axes if ax.get_title()]


def test_goal_in_3d_figure_and_animation_show_front_and_top_views(tmp_path, monkeypatch):
    """3D: two rows of four panels per method in the figure, two panels per method in the GIF, each
    title naming its view; the target in grey under every method panel; 2D keeps its one x-y view."""
    import imageio.v2 as imageio
    from matplotlib.colors import to_rgb

    metadata = generated_metadata("water3d")  # gravity along -y: front = x-y, top = x-z
    spacing = metadata["generator"]["params"]["spacing"]
    closed = closed_figures(monkeypatch)
    spec = GoalSpec(text="L", height=0.1, depth=2 * spacing, place="air", lift=0.1)
    results = run_goal({"R-GNS": RGNS(metadata, latent=16, layers=2)}, metadata, spec, tmp_path, steps=[2])
    figure = next(fig for fig in closed if fig._suptitle is not None)
    frames = [fig for fig in closed if fig._suptitle is None]
    methods = list(results["horizons"]["2"]["methods"])  # R-GNS, do nothing
    titles = panel_titles(figure)
    assert len(titles) == 2 * 4 * len(methods)  # a row per view and method, four columns (at most 6 a row)
    assert sum("front (x-y)" in t for t in titles) == sum("top (x-z)" in t for t in titles) == 4 * len(methods)
    grid = figure.axes[0].get_subplotspec().get_gridspec()
    assert grid.ncols == 4 and grid.nrows == 2 * len(methods)
    for ax in figure.axes:  # every panel but the target column: the target in light grey first, under the method
        if not ax.get_title().startswith("target"):
            grey = ax.collections[0].get_facecolor()[0]
            assert np.allclose(grey[:3], to_rgb("lightgrey"))
    assert frames and len(frames) == len(imageio.mimread(tmp_path / "goal_L_K2.gif"))
    for fig in frames:
        shown = panel_titles(fig)
        assert len(shown) == 2 * len(methods) and sum("front (x-y)" in t for t in shown) == len(methods)
        assert sum("top (x-z)" in t for t in shown) == len(methods)

    # gravity along -z: the front view is x against z, the top view x-y
    closed.clear()
    run_goal({"recorder": Recorder()}, dict(metadata, gravity=[0.0, 0.0, -9.81]), spec, tmp_path / "z_up",
             steps=[1], physics=False)
    titles = panel_titles(next(fig for fig in closed if fig._suptitle is not None))
    assert any("front (x-z)" in t for t in titles) and any("top (x-y)" in t for t in titles)
    # 2D: one row of four per method, no view names
    closed.clear()
    run_goal({"recorder": Recorder()}, METADATA, GoalSpec(text="L", height=0.05, place="centre"), tmp_path / "two",
             steps=[1], physics=False)
    figure = next(fig for fig in closed if fig._suptitle is not None)
    assert len(figure.axes) == 4 and not any("front" in t or "top" in t for t in panel_titles(figure))


def tiny_water3d(root: Path) -> Path:
    """A water3d dataset of one 4-frame trajectory per split, 20-60 particles (~9 s)."""
    from rgns.data.generate import generate_dataset

    params = OmegaConf.to_container(OmegaConf.load(CONF / "water3d.yaml"))
    params.update(particles=[20, 60], body_size=[0.05, 0.08], capacity=256, num_bodies=[1, 1])
    return generate_dataset(params, root, num_trajectories=1, num_frames=4, workers=1, progress=False,
                            splits=dict(valid=1, test=1))


def test_goal_text_list_runs_L_and_N_in_3d_as_separate_targets(tmp_path):
    """goal.text=[L,N]: each letter extruded and mid-air, run in turn by the task, into its own
    files and its own entry of the results; two texts that would share files are refused."""
    from types import SimpleNamespace

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from rgns.evaluation.tasks import Dataset
    from rgns.inverse.goal import GoalShaping, goal_specs

    with initialize_config_dir(str(CONF.parent), version_base="1.3"):
        cfg = compose("evaluate", overrides=["task=goal", "goal.text=[L,N]", "goal.steps=[2]", "task.goal.optimisers=null",
                                             f"output_dir={tmp_path}", "goal.height=0.1"])
    task = cfg.task.goal
    root = tiny_water3d(tmp_path / "tiny3d")
    dataset = Dataset.load(str(root), "test", 1, history=5, start=None)
    spacing, bounds = dataset.metadata["generator"]["params"]["spacing"], np.asarray(dataset.metadata["bounds"])
    goal = instantiate(task, _convert_="all")
    assert [spec.text for spec in goal.specs] == ["L", "N"]
    recorder = Recorder()
    results, _ = goal([SimpleNamespace(label="recorder", model=recorder)], dataset)

    assert list(results["targets"]) == ["L", "N"]
    L, N = results["targets"]["L"], results["targets"]["N"]
    assert {k: v for k, v in results.items() if k != "targets"} == L  # the first target's keys (report.md)
    assert L["goal"]["text"] == "L" and N["goal"]["text"] == "N" and L["particles"] != N["particles"]
    assert set(L["files"]) == {"goal_L_K2.png", "goal_L_K2.gif", "goal_L.json"}
    assert set(N["files"]) == {"goal_N_K2.png", "goal_N_K2.gif", "goal_N.json"}
    folder = tmp_path / f"goal_{dataset.name}"
    for name in L["files"] + N["files"]:
        assert (folder / name).stat().st_size > 0
    assert json.loads((folder / "goal_N.json").read_text())["goal"]["text"] == "N"
    # the report: a section per target, each linking its own figures
    from rgns.evaluation.report import goal_tables

    report = "\n".join(goal_tables({"datasets": {dataset.name: {"goal": json.loads(json.dumps(results))}}}))
    assert report.count("## Goal-conditioned shaping") == 2 and "'L'" in report and "'N'" in report
    assert f"goal_{dataset.name}/goal_N_K2.png" in report and f"goal_{dataset.name}/goal_L_K2.png" in report
    assert L["physics"]["solver"] == N["physics"]["solver"] == "SPH"
    for name in ("L", "N"):
        assert results["targets"][name]["horizons"]["2"]["methods"]["do nothing"]["solver"]["chamfer"] is not None
    # the states the inverse started from: L's target, then N's, each extruded along z and mid-air
    seen = [state.position.numpy() for state in recorder.seen[::2]]  # K = 2: two inverse steps per target
    assert [len(points) for points in seen] == [L["particles"], N["particles"]]
    for points in seen:
        assert points[:, 1].min() == pytest.approx(bounds[1, 0] + 0.1, abs=1e-6)  # the bottom 0.1 m above the floor
        layers = np.unique(points[:, 2].round(6))
        assert len(layers) == int(np.floor(0.1 / spacing + 1e-6))  # the default depth 0.1 m: floor(0.1 / h) layers
        assert layers.mean() == pytest.approx(bounds[2].mean(), abs=1e-6)  # centred in z
    with pytest.raises(ValueError, match="same files"):
        goal_specs(text=["L!", "L?"])
