"""Evaluation: the constant-velocity baseline, rollout stability, labels of a sweep, and
``evaluate.py`` on tiny trained checkpoints (files written, report numbers = results.json).
The other yardsticks (ballistic baseline, solver references) are in test_references.py."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import make_metadata, random_trajectory
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from PIL import Image

from rgns import config_dir
from rgns.data.contract import SPLITS, WATER, write_metadata, write_split
from rgns.evaluation.baselines import Ballistic, ConstantVelocity
from rgns.evaluation.methods import Method, _disambiguate, describe, find_checkpoints
from rgns.evaluation.metrics import density_ratio
from rgns.evaluation.compare import main as compare
from rgns.evaluation.freefall import internal_accelerations
from rgns.evaluation.rest import settled_pool
from rgns.evaluation.walls import at_the_walls
from rgns.evaluation.run import evaluate
from rgns.evaluation.tasks import Dataset, ForwardRollout, InverseConsistency, in_parallel
from rgns.inverse.tasks import chosen_optimisers
from rgns.training.rollouts import forward_rollout, inverse_then_forward

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")
FRAMES = 30
FAST = ["trajectories=2", "task.forward.distribution_steps=[1,10]", "task.efficiency.repeats=1",
        "task.inverse.horizons=[1,5,10,20]", "task.inverse.table_horizon=10", "animation.max_frames=6"]


def linear_trajectory(frames: int, speed: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Particles moving at constant velocity to the right, starting inside the box."""
    rng = np.random.default_rng(1)
    start = rng.uniform(0.3, 0.5, (20, 2))
    t = np.arange(frames)[:, None, None]
    position = start[None] + t * np.array([speed, 0.0])
    return torch.tensor(position, dtype=torch.float32), torch.full((20,), WATER)


def test_constant_velocity_is_exact_on_linear_motion_both_ways():
    position, particle_type = linear_trajectory(30, 1e-3)
    model = ConstantVelocity(make_metadata(frames=30))
    assert sum(p.numel() for p in model.parameters()) == 0
    inferred, resimulated = inverse_then_forward(model, position, particle_type, start=5, steps=20)
    torch.testing.assert_close(inferred[-1], position[5], atol=1e-6, rtol=0)
    torch.testing.assert_close(resimulated, position[6:26], atol=1e-6, rtol=0)


def test_forward_task_reports_where_a_rollout_leaves_the_box():
    """Truth and baseline both fly out of the box at 0.02 per frame: zero error, yet broken."""
    position, particle_type = linear_trajectory(40, 0.02)
    metadata = make_metadata(frames=40)
    dataset = Dataset("linear", "", metadata, [(position, particle_type)], start=5)
    method = Method("Const. velocity", ConstantVelocity(metadata), None, "baseline")
    results, examples = ForwardRollout(steps=None, distribution_steps=[1, 10])([method], dataset)
    row = results["methods"]["Const. velocity"]
    assert row["rollout_mse"] == pytest.approx(0.0, abs=1e-10)
    # x starts <= 0.5 + 5 * 0.02 and passes 0.9 + 2 radii (0.16) within 34 steps
    assert row["diverged"] and 0 < row["stable_steps"] < 34
    assert examples["predicted"]["Const. velocity"].shape == (34, 20, 2)
    inverse, _ = InverseConsistency(horizons=[1, 5, 100], threshold=1e-3)([method], dataset)
    assert inverse["settings"]["horizons"] == [1, 5]  # K = 100 does not fit in 40 frames
    assert inverse["methods"]["Const. velocity"]["horizons"][5]["inverse_mse"] == pytest.approx(0.0, abs=1e-10)


def test_density_at_the_end_compares_neighbour_counts():
    """Predicted over true mean neighbours: 1 for the truth itself, above 1 for a compressed copy
    (counted here by brute force), 0 for one spread past the radius, None for a blown-up one."""
    lattice = torch.stack(torch.meshgrid(torch.arange(10.0), torch.arange(10.0), indexing="ij"), -1).reshape(-1, 2) * 0.01
    radius = 0.0105  # 4 neighbours inside, 3 on edges, 2 at corners: 3.6 on the mean
    squeezed = 0.6 * lattice  # spacing 0.006: the diagonals (0.0085) come within the radius too

    def brute_force(position):
        distance = torch.cdist(position.double(), position.double())
        return float(((distance < radius).sum() - len(position)) / len(position))

    assert brute_force(lattice) == pytest.approx(3.6)
    ratio = density_ratio(squeezed, lattice, radius)
    assert ratio == pytest.approx(brute_force(squeezed) / 3.6) and ratio > 1.5
    assert density_ratio(lattice, lattice, radius) == pytest.approx(1.0)
    assert density_ratio(2.0 * lattice, lattice, radius) == 0.0
    blown_up = lattice.clone()
    blown_up[3] = float("nan")
    assert density_ratio(blown_up, lattice, radius) is None


def test_settled_pool_finds_a_simulator_that_squeezes_the_water():
    """A lattice at rest stays at rest under constant velocity (x1, no displacement); one whose
    last frames contract towards its centre keeps contracting under it: denser, and each particle
    moves on by its last velocity times the steps, while the truth's own drift is measured too."""
    lattice = torch.stack(torch.meshgrid(torch.arange(8.0), torch.arange(8.0), indexing="ij"), -1).reshape(-1, 2)
    lattice = 0.4 + 0.01 * lattice  # spacing 0.01 inside the box
    metadata, radius, steps = make_metadata(frames=30), 0.0105, 10
    model, types = ConstantVelocity(metadata), torch.full((64,), WATER)
    at_rest = settled_pool(model, lattice.expand(30, -1, -1), types, steps, radius)
    for who in ("model", "truth"):
        assert at_rest[who]["neighbours_ratio"] == pytest.approx(1.0)
        assert at_rest[who]["rms_displacement"] == pytest.approx(0.0, abs=1e-7)
    centre = lattice.mean(0)
    scale = torch.linspace(1.0, 0.8, 30)[:, None, None]  # 0.69% closer each frame
    shrinking = centre + scale * (lattice - centre)
    squeezed = settled_pool(model, shrinking, types, steps, radius)
    assert squeezed["model"]["neighbours_ratio"] > 1.5  # spacing 0.008 -> 0.0073: the diagonals come within R
    last_velocity = shrinking[-1] - shrinking[-2]
    expected = float((steps * last_velocity).pow(2).sum(-1).mean().sqrt())
    assert squeezed["model"]["rms_displacement"] == pytest.approx(expected, rel=1e-4)
    assert squeezed["truth"]["rms_displacement"] == pytest.approx(expected, rel=1e-4)  # the same contraction
    with pytest.raises(ValueError, match="too short"):
        settled_pool(model, shrinking[:8], types, steps, radius)


def test_at_the_walls_finds_water_pushed_into_the_floor():
    """A row of particles falls at constant speed and the truth stops it 1 mm above the floor;
    constant velocity carries it on into the floor, where the hard wall stops it: the closest
    approach, the share near the wall and the heights tell them apart, and the error, a uniform
    offset of every particle, is all the centre of mass's."""
    metadata = make_metadata(frames=30)  # box [0.1, 0.9] on both axes
    x = 0.3 + 0.01 * torch.arange(10.0)
    height = (0.2 - 0.005 * torch.arange(30.0)).clamp(min=0.101)  # 0.5 cm a frame down to 1 mm above the floor
    truth = torch.stack([x.expand(30, -1), height[:, None].expand(-1, 10)], dim=-1)  # [30, 10, 2]
    model, types = ConstantVelocity(metadata), torch.full((10,), WATER)
    model.hard_walls = True
    rows = at_the_walls(model, truth, types, start=5, steps=[0, 20, 40], near=0.0005)
    assert [row["step"] for row in rows] == [0, 20]  # step 40 is past the trajectory's end
    first, late = rows
    assert first["error"] == pytest.approx(0.0, abs=1e-12) and first["model"]["closest"] == pytest.approx(0.07, abs=1e-6)
    assert late["truth"]["closest"] == pytest.approx(0.001, abs=1e-6) and late["truth"]["near_fraction"] == 0.0
    assert late["model"]["closest"] == 0.0 and late["model"]["near_fraction"] == 1.0
    assert late["model"]["height"] == pytest.approx(0.0) and late["truth"]["height"] == pytest.approx(0.001, abs=1e-6)
    assert late["error"] == pytest.approx(1e-6, rel=1e-3) and late["centre_share"] == pytest.approx(1.0, rel=1e-4)
    # float32 positions: differences good to about 1e-7
    assert first["model"]["speed"] == pytest.approx(0.005, abs=1e-7)
    assert first["truth"]["speed"] == pytest.approx(0.005, abs=1e-7)
    assert late["model"]["speed"] == 0.0 and late["truth"]["speed"] == 0.0  # stopped by the hard wall, and by the truth


def test_at_the_walls_speed_is_the_rollouts_own():
    """Speeds are each rollout's own frame differences: a model that keeps moving where the
    truth has stopped shows its speed against the truth's zero."""
    metadata = make_metadata(frames=30)
    shift = 0.002 * torch.arange(30.0).clamp(max=7)  # 2 mm a frame to the right, stopped from frame 7 on
    still = 0.5 + torch.stack([shift, torch.zeros(30)], dim=-1)[:, None, :].expand(30, 4, 2)
    model, types = ConstantVelocity(metadata), torch.full((4,), WATER)
    rows = at_the_walls(model, still, types, start=7, steps=[0, 10], near=0.0005)
    for row in rows:
        assert row["truth"]["speed"] == 0.0 and row["model"]["speed"] == pytest.approx(0.002, abs=1e-7)


def test_walls_main_rolls_the_figure_trajectory_out_once(tmp_path, monkeypatch):
    """With ``--figure``, the figure's trajectory is rolled out once, to the later of the two step
    lists, and its rows are the ones a run without the figure reports."""
    from types import SimpleNamespace

    import rgns.evaluation.methods as methods
    from rgns.evaluation import walls

    metadata = make_metadata(frames=30)
    x = 0.3 + 0.01 * torch.arange(10.0)
    trajectories = []
    for speed in (0.004, 0.006):
        height = (0.4 - speed * torch.arange(30.0)).clamp(min=0.101)
        trajectories.append((torch.stack([x.expand(30, -1), height[:, None].expand(-1, 10)], dim=-1),
                             torch.full((10,), WATER)))
    model = ConstantVelocity(metadata)
    horizons = []
    rollout = model.rollout
    monkeypatch.setattr(model, "rollout", lambda state, horizon, *a: horizons.append(horizon) or rollout(state, horizon, *a))
    dataset = SimpleNamespace(trajectories=trajectories, start=5, metadata=metadata)
    monkeypatch.setattr(methods, "load_checkpoint_on_split", lambda args: (model, tmp_path, dataset))
    plain = walls.main(["unused.ckpt", "--steps", "0", "10"])
    assert horizons == [11, 11]
    horizons.clear()
    figure = tmp_path / "walls.png"
    drawn = walls.main(["unused.ckpt", "--steps", "0", "10", "--figure", str(figure), "--figure-trajectory", "1",
                        "--figure-steps", "5", "20"])
    assert horizons == [11, 21] and figure.stat().st_size > 0  # trajectory 1 once, to step 20
    assert drawn["trajectories"] == plain["trajectories"]


def falling_body(frames: int = 12, seed: int = 0) -> torch.Tensor:
    """A loose body of 30 particles in the middle of the box, falling ballistically at about
    3e-3 per frame sideways: a rigid motion, so its true internal acceleration is zero. ``[T, 30, 2]``"""
    generator = torch.Generator().manual_seed(seed)
    shape = 0.45 + 0.1 * torch.rand(30, 2, generator=generator, dtype=torch.float64)
    t = torch.arange(frames, dtype=torch.float64)[:, None]
    centre = torch.cat([3e-3 * t, -0.5 * 6.1e-5 * t**2], dim=-1)  # [T, 2]
    return (shape[None] + centre[:, None]).float()


def test_free_fall_internal_accelerations_tell_galilean_pair_terms_apart():
    """Constant velocity adds no internal acceleration at any speed and the rigid truth has none;
    a Galilean R-GNS far from the walls adds the same at every speed of the body, the same network
    without the option adds a different one at each."""
    from rgns.models import RGNS

    position, types = falling_body(), torch.full((30,), WATER)
    metadata = dict(make_metadata(radius=0.05), gravity=[0.0, -9.81])
    still = internal_accelerations(ConstantVelocity(metadata), position, types, frame=6, speeds=[0.0, 1.0, 2.0])
    assert still["model"] == {0.0: 0.0, 1.0: 0.0, 2.0: 0.0}
    assert still["truth"] < 3e-7  # float32 round-off of second differences near 0.5, against gravity's 6.1e-5
    assert still["speed"] == pytest.approx(float(torch.tensor([3e-3, -6.1e-5 * 5.5]).norm()), rel=1e-3)
    found = {}
    for galilean in (True, False):
        torch.manual_seed(0)
        model = RGNS(metadata, latent=16, layers=2, couplings="pairwise", galilean=galilean, zero_init=False)
        found[galilean] = internal_accelerations(model, position, types, frame=6, speeds=[0.0, 1.0, 2.0])["model"]
    assert min(found[True].values()) > 1e-6  # the network does push the particles about
    assert max(found[True].values()) - min(found[True].values()) < 1e-3 * max(found[True].values())
    assert max(found[False].values()) - min(found[False].values()) > 1e-2 * max(found[False].values())
    with pytest.raises(ValueError, match="frame"):
        internal_accelerations(model, position, types, frame=2, speeds=[1.0])  # no full history before it


def test_free_fall_diagnostic_runs_on_a_checkpoint(trained, tmp_path):
    from rgns.evaluation.freefall import main as freefall

    checkpoint = next((trained / "sweep").glob("*/checkpoints/last.ckpt"))
    result = freefall([str(checkpoint), "--trajectories", "2", "--speeds", "0", "1", "--json", str(tmp_path / "f.json")])
    assert len(result["trajectories"]) == 2 and set(result["summary"]["model"]) == {0.0, 1.0}
    assert json.loads((tmp_path / "f.json").read_text())["frame"] == 6
    with pytest.raises(SystemExit):
        freefall([str(checkpoint), "--frame", "1"])


def pid_after(job: int) -> tuple[int, int]:
    time.sleep(0.05)  # long enough that a forked worker gets some of the jobs
    return job * job, os.getpid()


def test_jobs_in_parallel_give_the_serial_results_and_keep_pinned_jobs_here():
    jobs = list(range(12))
    done = in_parallel(jobs, pid_after, here=[0, 5], workers=2)
    assert [value for value, _ in done] == [j * j for j in jobs]
    assert done[0][1] == done[5][1] == os.getpid()  # the pinned jobs ran in this process
    assert {pid for _, pid in done} - {os.getpid()}  # a worker took some of the others
    assert in_parallel(jobs, pid_after, here=[], workers=1) == [(j * j, os.getpid()) for j in jobs]


def fails_on_seven(job: int) -> int:
    if job == 7 and os.getpid() != PARENT:
        raise ValueError("planted failure")
    pid_after(job)  # the pinned jobs keep this process busy while the worker takes job 7
    return job


PARENT = os.getpid()


def test_a_workers_error_reaches_the_caller_with_its_traceback():
    with pytest.raises(RuntimeError, match="planted failure"):
        in_parallel(list(range(8)), fails_on_seven, here=list(range(7)), workers=2)  # job 7 is the worker's


class FakeReference:
    """A solver reference's shape: no network (``model = None``), rollouts from its own state."""

    label, model, trained, bidirectional = "Fake solver", None, False, False

    def __init__(self, metadata):
        self.baseline, self.pid = Ballistic(metadata), set()

    def forward_rollout(self, dataset, index, steps):
        self.pid.add(os.getpid())  # kept here only if it ran here
        position, particle_type = dataset.trajectories[index]
        return forward_rollout(self.baseline, position, particle_type, dataset.start, steps)


def test_forward_rollouts_in_two_processes_give_the_same_results():
    metadata = make_metadata(frames=40)
    trajectories = [linear_trajectory(40, speed) for speed in (0.0, 0.005, 0.01, 0.02)]  # the last one reaches a wall
    dataset = Dataset("linear", "", metadata, trajectories, start=5)
    reference = FakeReference(metadata)
    methods = [Method("Const. velocity", ConstantVelocity(metadata), None, "baseline"),
               Method("Ballistic + walls", Ballistic(metadata), None, "baseline"), reference]
    task = dict(steps=30, distribution_steps=[1, 10])
    serial, serial_examples = ForwardRollout(**task)(methods, dataset)
    parallel, parallel_examples = ForwardRollout(**task, workers=2)(methods, dataset)
    assert parallel == serial
    assert reference.pid == {os.getpid()}  # the reference ran here both times
    for label, frames in serial_examples["predicted"].items():
        torch.testing.assert_close(parallel_examples["predicted"][label], frames, rtol=0, atol=0)
    torch.testing.assert_close(parallel_examples["truth"], serial_examples["truth"], rtol=0, atol=0)
    assert serial["methods"]["Ballistic + walls"]["rollout_mse"] != serial["methods"]["Const. velocity"]["rollout_mse"]


def test_labels_follow_the_paper_and_sweeps_stay_apart():
    assert describe({"_target_": "rgns.models.RGNS", "latent": 128, "layers": 10}) == "R-GNS 128x10"
    assert describe({"_target_": "rgns.models.RGNS", "latent": 64, "layers": 5, "train_inverse": False}) == "R-GNS† 64x5"
    assert describe({"_target_": "rgns.models.RGNS", "latent": 8, "layers": 2, "encoder": "mlp"}) == "R-GNS 8x2 MLP enc."
    # the basis where it is not the model's usual one (conf/model/): GNS reads velocities, R-GNS differences
    assert describe({"_target_": "rgns.models.GNS", "latent": 32, "layers": 4, "basis": "differences"}) == \
        "GNS 32x4 differences basis"
    assert describe({"_target_": "rgns.models.SepGNS", "latent": 32, "layers": 4, "basis": "differences"}) == \
        "Sep-GNS 32x4 differences basis"
    assert describe({"_target_": "rgns.models.GNS", "latent": 32, "layers": 4, "basis": "velocity"}) == "GNS 32x4"
    assert describe({"_target_": "rgns.models.GNS", "latent": 32, "layers": 4, "edge_velocity": True}) == \
        "GNS 32x4 edge velocity"
    assert describe({"_target_": "rgns.models.SepGNS", "latent": 32, "layers": 4, "decoder": "pairwise"}) == \
        "Sep-GNS 32x4 pairwise decoder"
    assert describe({"_target_": "rgns.models.RGNS", "latent": 32, "layers": 2, "basis": "differences"}) == "R-GNS 32x2"
    assert describe({"_target_": "rgns.models.RGNS", "latent": 32, "layers": 2, "basis": "velocity"}) == \
        "R-GNS 32x2 velocity basis"
    methods = [Method("R-GNS 16x2", None, None, f"/m/{i}/checkpoints/last.ckpt",
                      dict(overrides=["model.latent=16", f"loss={loss}"])) for i, loss in enumerate(("dl1", "dl4"))]
    _disambiguate(methods)
    assert [m.label for m in methods] == ["R-GNS 16x2 (loss=dl1)", "R-GNS 16x2 (loss=dl4)"]


@pytest.mark.parametrize("task, names", [("forward", ["forward", "efficiency"]), ("inverse", ["inverse", "efficiency"]),
                                         ("all", ["forward", "efficiency", "inverse"])])
def test_task_configs_compose_and_instantiate(task, names):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"task={task}", "divergence.energy_factor=7"])
    tasks = [instantiate(c) for c in cfg.task.values()]
    assert [t.name for t in tasks] == names
    assert all(t.divergence.energy_factor == 7 for t in tasks if hasattr(t, "divergence"))


@pytest.mark.parametrize("task", ["inverse_optimisation", "goal"])
@pytest.mark.parametrize("override, kinds", [(None, {"sph", "mpm"}), ("optimisers=null", set()),
                                              ("optimisers.mpm=null", {"sph"}), ("optimisers={}", {"sph", "mpm"})])
def test_optimisers_are_left_out_by_null(tmp_path, task, override, kinds):
    """``task.<task>.optimisers=null`` runs no optimiser and ``optimisers.mpm=null`` all but MPM, in
    both tasks that have them (``optimisers={}`` merges into the preset's mapping: Hydra's rule, kept)."""
    extra = [f"task.{task}.{override}"] if override else []
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"task={task}", f"output_dir={tmp_path}", *extra])
    made = instantiate(cfg.task[task], _convert_="all")
    chosen = made.settings["optimisers"] if task == "inverse_optimisation" else chosen_optimisers(made.optimisers)
    assert set(chosen) - {"learned"} == kinds
    assert all(isinstance(options, dict) for options in chosen.values())


def test_checkpoints_are_found_under_a_sweep_folder(tmp_path):
    for run, files in (("0", ("last.ckpt", "best-step=5.ckpt")), ("1", ("last.ckpt",)), ("2/.hydra", ())):
        (tmp_path / run / "checkpoints").mkdir(parents=True)
        for name in files:
            (tmp_path / run / "checkpoints" / name).write_bytes(b"")
    last = find_checkpoints(checkpoints_dir=str(tmp_path))
    assert [p.relative_to(tmp_path).as_posix() for p in last] == ["0/checkpoints/last.ckpt", "1/checkpoints/last.ckpt"]
    best = find_checkpoints(checkpoints_dir=str(tmp_path), checkpoint="best")
    assert [p.name for p in best] == ["best-step=5.ckpt"]
    with pytest.raises(FileNotFoundError):
        find_checkpoints(ckpt_path=str(tmp_path / "missing.ckpt"))


# ---- evaluate.py on tiny trained checkpoints --------------------------------------------------

@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A 30-frame dataset and a sweep of two tiny models (R-GNS, GNS), 10 training steps each."""
    root = tmp_path_factory.mktemp("evaluate")
    data = root / "data"
    rng = np.random.default_rng(0)
    for split, count in zip(SPLITS, (3, 2, 2)):
        write_split(data / f"{split}.h5", [random_trajectory(rng, frames=FRAMES) for _ in range(count)])
    write_metadata(data, make_metadata(frames=FRAMES))
    subprocess.run(
        [sys.executable, "train.py", "-m", "data=folder", f"data.root={data}", "model=rgns,gns", "model.latent=16",
         "model.layers=2", "trainer=cpu", "trainer.max_steps=10", "trainer.val_check_interval=5",
         "data.num_workers=0", "logger=tensorboard", f"hydra.sweep.dir={root / 'sweep'}"],
        cwd=ROOT, env=ENV, check=True, capture_output=True, timeout=300)
    return root


def markdown_tables(text: str) -> dict[str, dict[str, list[str]]]:
    """Each table of a markdown text, keyed by the heading above it: {first cell: cells} (row
    of the header included under its own first cell)."""
    tables, heading = {}, None
    for block in re.split(r"\n\s*\n", text):
        lines = block.strip().splitlines()
        if lines and lines[0].startswith("#"):
            heading = lines[0].lstrip("# ")
        elif lines and lines[0].startswith("|"):
            rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines if not line.startswith("|---")]
            tables[heading if heading not in tables else f"{heading} #{len(tables)}"] = {r[0]: r[1:] for r in rows}
    return tables


def value(cell: str) -> float:
    return float(cell.replace("**", "").replace("≥", "").strip())


def assert_cells(table: dict[str, list[str]], row: str, expected: dict[str, float | None], scale: float = 1.0):
    labels = table[next(iter(table))]  # the header row
    for label, cell in zip(labels, table[row]):
        if expected.get(label) is None:
            assert cell == "—", (row, label, cell)
        else:
            assert value(cell) == pytest.approx(expected[label] * scale, rel=1e-3, abs=1e-12), (row, label, cell)


def test_evaluate_sweep_writes_report_json_and_charts(trained):
    out = trained / "report"
    subprocess.run([sys.executable, "evaluate.py", f"checkpoints_dir={trained / 'sweep'}", *FAST,
                    f"hydra.run.dir={out}"], cwd=ROOT, env=ENV, check=True, capture_output=True, timeout=300)
    for name in ("results.json", "report.md", "accuracy_vs_speed.png", "error_vs_step.png", "consistency_vs_k.png"):
        assert (out / name).stat().st_size > 0, name
    for name in ("accuracy_vs_speed.png", "error_vs_step.png", "consistency_vs_k.png"):
        assert Image.open(out / name).size[0] > 500
    for name in ("forward_data.gif", "inverse_data.gif"):
        assert Image.open(out / name).n_frames > 2

    results = json.loads((out / "results.json").read_text())
    data = results["datasets"]["data"]
    assert set(data["forward"]["methods"]) == {"R-GNS 16x2", "GNS 16x2", "Const. velocity", "Ballistic + walls"}
    assert set(data["inverse"]["methods"]) == {"R-GNS 16x2", "Const. velocity", "Ballistic + walls"}  # GNS: forward only
    # a dataset without a generator (as converted ones): no solver to re-run, and the report says why
    assert data["references"]["methods"] == {} and "no generator" in data["references"]["note"]
    forward, inverse, cost, summary = (data[k]["methods"] if k != "summary" else data[k]
                                       for k in ("forward", "inverse", "efficiency", "summary"))
    steps = FRAMES - 1 - 5
    assert data["forward"]["settings"]["steps"] == steps and len(forward["GNS 16x2"]["mse_per_step"]) == steps
    assert data["inverse"]["settings"]["horizons"] == [1, 5, 10, 20]
    assert inverse["R-GNS 16x2"]["horizons"]["5"]["inverse_mse"] == 0.0  # frame t0 is in the history when K <= k
    assert cost["R-GNS 16x2"]["parameters"] < cost["GNS 16x2"]["parameters"]  # half of a GNS, as in the paper
    assert all(row["forward_ms_per_step"] > 0 for row in cost.values())

    report = (out / "report.md").read_text()
    assert f"data: {data['references']['note']}" in report
    tables = markdown_tables(report)
    K = data["inverse"]["settings"]["table_horizon"]
    assert_cells(tables["Rollout MSE (1e-3) in the forward process"], "data",
                 {m: r["rollout_mse"] for m, r in forward.items()}, 1e3)
    efficiency = tables["Efficiency comparison on data"]
    assert_cells(efficiency, "Parameter Count (M)", {m: r["parameters"] for m, r in cost.items()}, 1e-6)
    assert_cells(efficiency, "Forward Inference Time (ms/step)", {m: r["forward_ms_per_step"] for m, r in cost.items()})
    assert_cells(efficiency, "Inverse Inference Time (ms/step)", {m: r.get("inverse_ms_per_step") for m, r in cost.items()})
    assert_cells(efficiency, "Inference Memory (MB)", {m: r["forward_memory_mb"] for m, r in cost.items()})
    comparison = tables[f"Inverse inference comparison on data (inverse step = {K})"]
    assert_cells(comparison, "Consistency MSE (1e-3)",
                 {m: r["horizons"][str(K)]["consistency_mse"] for m, r in inverse.items()}, 1e3)
    assert_cells(comparison, "Inverse MSE (1e-3)", {m: r["horizons"][str(K)]["inverse_mse"] for m, r in inverse.items()}, 1e3)
    assert_cells(comparison, f"Inference Time, {K} inverse steps (s)",
                 {m: K * cost[m]["inverse_ms_per_step"] / 1e3 for m in inverse})
    assert_cells(comparison, "Max Stable Steps", {m: r["max_stable_steps"] for m, r in inverse.items()})
    by_k = tables[f"Consistency and inverse MSE (1e-3) against the inverse steps K on data"]
    for k in ("1", "10", "20"):
        assert_cells(by_k, k, {f"Consistency {m}": r["horizons"][k]["consistency_mse"] for m, r in inverse.items()}
                     | {f"Inverse {m}": r["horizons"][k]["inverse_mse"] for m, r in inverse.items()}, 1e3)
    assert summary["R-GNS 16x2"]["rollout_mse"] == forward["R-GNS 16x2"]["rollout_mse"]
    assert results["command"].startswith("python evaluate.py checkpoints_dir=")
    # the paired comparison reads this file: its ratio is the rollout MSEs' (the baselines left out of the choice)
    _, gns = compare([f"R={out}#R-GNS 16x2", f"G={out}#GNS 16x2", "--resamples", "10"])
    assert gns["ratio"] == pytest.approx(forward["GNS 16x2"]["rollout_mse"] / forward["R-GNS 16x2"]["rollout_mse"])


def test_evaluate_one_checkpoint_forward_task_only(trained, tmp_path):
    checkpoint = next((trained / "sweep").glob("*/checkpoints/last.ckpt"))
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"ckpt_path={checkpoint}", "task=forward", f"output_dir={tmp_path}",
                                             "task.forward.steps=8", "baselines=null", *FAST[:2], "task.efficiency=null"])
    results = evaluate(cfg)
    data = results["datasets"]["data"]
    assert "inverse" not in data and "efficiency" not in data and data["forward"]["settings"]["steps"] == 8
    assert len(data["forward"]["methods"]) == 1  # no baseline
    report = (tmp_path / "report.md").read_text()
    assert "Inverse inference comparison" not in report and "forward_data.gif" in report
    assert not (tmp_path / "consistency_vs_k.png").exists() and (tmp_path / "error_vs_step.png").is_file()
    (row,) = data["forward"]["methods"].values()
    density = markdown_tables(report)["Forward rollouts on data"]
    (label,) = [key for key in density if key != "Method"]
    column = density["Method"].index("Density at the end (predicted / true)")
    assert value(density[label][column]) == pytest.approx(row["density_end"], abs=0.006)


def test_rest_diagnostic_runs_on_a_checkpoint(trained, tmp_path):
    from rgns.evaluation.rest import main as rest

    checkpoint = next((trained / "sweep").glob("*/checkpoints/last.ckpt"))
    result = rest([str(checkpoint), "--steps", "5", "--trajectories", "2", "--json", str(tmp_path / "rest.json")])
    assert len(result["trajectories"]) == 2 and result["steps"] == 5
    assert json.loads((tmp_path / "rest.json").read_text())["summary"] == result["summary"]
    assert all(row["model"]["rms_displacement"] > 0 for row in result["trajectories"])  # random data is not at rest
    with pytest.raises(SystemExit):
        rest([str(checkpoint), "--steps", "0"])


def test_where_finds_the_step_and_the_particles_that_make_the_error():
    from rgns.evaluation.where import error_steps

    truth = torch.zeros(10, 5, 2)
    truth[:, :, 0] = torch.arange(5.0)  # particle j sits at x = j
    predicted = truth.clone()
    predicted[6:, 3, 1] -= 0.5  # particle 3 too low from step 7 on
    particle_type = torch.tensor([5, 5, 5, 5, 3])  # the last one kinematic
    predicted[:, 4, 1] += 9.0  # a kinematic particle's error is never among the worst
    result = error_steps(predicted, truth, particle_type, every=3, worst=1)
    assert [row["step"] for row in result["rows"]] == [3, 6, 9, 10]  # the last step always
    assert result["rollout_mse"] == pytest.approx(float((predicted - truth).pow(2).mean()))
    first, _, third, last = result["rows"]
    assert first["mse"] == pytest.approx(81 / 10) and third["mse"] == pytest.approx((81 + 0.25) / 10)
    assert third["truth"] == [3.0, 0.0] and third["predicted"] == [3.0, -0.5]
    assert first["share"] == pytest.approx(3 * 8.1 / (10 * 8.1 + 4 * 0.025)) and last["share"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="every=0"):
        error_steps(predicted, truth, particle_type, every=0, worst=1)


def test_where_diagnostic_runs_on_a_checkpoint(trained, tmp_path, capsys):
    from rgns.evaluation.where import main as where

    checkpoint = next((trained / "sweep").glob("*/checkpoints/last.ckpt"))
    result = where([str(checkpoint), "--steps", "6", "--every", "4", "--worst", "3", "--trajectories", "2",
                    "--only", "1", "--json", str(tmp_path / "where.json")])
    assert list(result["trajectories"]) == [1] and [r["step"] for r in result["trajectories"][1]["rows"]] == [4, 6]
    assert json.loads((tmp_path / "where.json").read_text())["trajectories"]["1"]["rows"][-1]["share"] == pytest.approx(1.0)
    assert "trajectory 1 (" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        where([str(checkpoint), "--trajectories", "2", "--only", "2"])


def test_walls_diagnostic_runs_on_a_checkpoint(trained, tmp_path):
    from rgns.evaluation.walls import main as walls

    checkpoint = next((trained / "sweep").glob("*/checkpoints/last.ckpt"))
    result = walls([str(checkpoint), "--steps", "2", "4", "--trajectories", "2", "--json", str(tmp_path / "walls.json"),
                    "--figure", str(tmp_path / "walls.png"), "--figure-steps", "1", "3"])
    assert [len(rows) for rows in result["trajectories"]] == [2, 2] and result["hard_walls"]
    assert json.loads((tmp_path / "walls.json").read_text())["summary"].keys() == {"2", "4"}
    assert Image.open(tmp_path / "walls.png").size[0] > 0
    with pytest.raises(SystemExit):
        walls([str(checkpoint), "--near", "0"])


def test_evaluate_goal_task_writes_figure_gif_and_matching_table(trained, tmp_path):
    checkpoint = next((trained / "sweep").glob("*/checkpoints/last.ckpt"))
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"ckpt_path={checkpoint}", "task=goal", "goal.text=L", "goal.height=0.1",
                                             "goal.steps=[2,3]", "task.goal.optimisers=null", "baselines=null",
                                             f"output_dir={tmp_path}", "trajectories=1"])
    results = evaluate(cfg)
    goal = results["datasets"]["data"]["goal"]
    assert {"goal_L_K2.png", "goal_L_K3.gif"} <= set(goal["files"])
    assert all((tmp_path / "goal_data" / f).is_file() for f in goal["files"])
    assert goal["goal"]["place"] == "air" and goal["physics"]["solver"] is None  # the tiny dataset has no generator
    assert "no generator" in goal["physics"]["note"] and goal["physics"]["train_max_speed"] > 0
    tables = markdown_tables((tmp_path / "report.md").read_text())
    for K in ("2", "3"):
        (label,) = goal["horizons"][K]["methods"]
        table = tables[f"K = {K}"]  # the first table under the heading; the plausibility table follows it
        cells = dict(zip(table["Method"], table[label]))
        metrics = goal["horizons"][K]["methods"][label]["model"]
        assert value(cells["Chamfer by model (1e-5)"]) == pytest.approx(metrics["chamfer"] * 1e5, rel=1e-3)
        assert value(cells["OT by model (1e-3)"]) == pytest.approx(metrics["ot"] * 1e3, rel=1e-3)
        assert cells["Chamfer by solver (1e-5)"] == "—"


def test_two_dataset_folders_of_one_name_stay_apart(trained, tmp_path, monkeypatch):
    """Checkpoints trained on two folders both called 'data' get two sections, not one overwritten."""
    import shutil

    import rgns.evaluation.run as run_module
    from rgns.evaluation.methods import load_checkpoints

    checkpoint = next((trained / "sweep").glob("*/checkpoints/last.ckpt"))
    twin = tmp_path / "elsewhere" / "data"
    shutil.copytree(trained / "data", twin)
    loaded = load_checkpoints([checkpoint], "cpu") + load_checkpoints([checkpoint], "cpu")
    loaded[1].data_root = str(twin)
    monkeypatch.setattr(run_module, "load_checkpoints", lambda paths, device, **_: loaded)
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"ckpt_path={checkpoint}", "task=forward", f"output_dir={tmp_path / 'out'}",
                                             "task.forward.steps=4", "baselines=null", *FAST[:3]])
    results = evaluate(cfg)
    assert sorted(results["datasets"]) == ["data", "data_2"]
    assert {d["root"] for d in results["datasets"].values()} == {str((trained / "data").resolve()), str(twin.resolve())}


def test_animation_shows_particles_that_leave_the_box(tmp_path):
    import imageio.v3 as iio

    from rgns.evaluation.plots import animate

    bounds = [[0.1, 0.9], [0.1, 0.9]]
    inside = np.full((3, 4, 2), 0.5)
    escaped = inside.copy()
    escaped[1:, 0] = [5.0, -3.0]  # far outside from frame 1 on
    escaped[2, 1] = np.nan
    animate({"truth": inside, "model": escaped}, ["a", "b", "c"], np.zeros(4, dtype=int), bounds,
            tmp_path / "a.gif", max_frames=10, fps=5)
    frames = iio.imread(tmp_path / "a.gif", index=None)
    assert frames.shape[0] == 3

    def red(frame):  # tab:red is (214, 39, 40)
        return ((frame[..., 0] > 180) & (frame[..., 1] < 90) & (frame[..., 2] < 90)).sum()

    assert red(frames[0]) == 0 and red(frames[1]) > 0 and red(frames[2]) > red(frames[1]) * 1.5


def test_an_animation_of_many_methods_is_a_grid_of_at_most_six_a_row(tmp_path):
    import imageio.v3 as iio

    from rgns.evaluation.plots import animate

    panels = {f"m{i}": np.full((2, 4, 2), 0.5) for i in range(13)}
    animate(panels, ["a", "b"], np.zeros(4, dtype=int), [[0.1, 0.9], [0.1, 0.9]], tmp_path / "a.gif", 10, 5)
    animate(dict(list(panels.items())[:6]), ["a", "b"], np.zeros(4, dtype=int), [[0.1, 0.9], [0.1, 0.9]],
            tmp_path / "b.gif", 10, 5)
    grid, row = iio.imread(tmp_path / "a.gif", index=0), iio.imread(tmp_path / "b.gif", index=0)
    assert grid.shape[1] == row.shape[1]  # 6 columns in both
    assert grid.shape[0] > 2.5 * row.shape[0]  # 13 panels: 3 rows


def test_the_headline_animation_and_the_colours_group_each_methods_variants():
    from rgns.evaluation.plots import _colours, headline_panels

    labels = ["R-GNS 32x2", "R-GNS 32x2, no hard walls", "GNS 32x4", "Sep-GNS 32x4", "R-GNS 128x2 pretrained",
              "GNS 64x4 pretrained", "R-GNS† 32x2 pretrained", "constant velocity", "MPM 32 cells/m",
              "MPM 48 cells/m", "MPM floor (1e-4 m)"]
    solvers = {"MPM 32 cells/m": {"n_grid": 32, "perturbation": None},
               "MPM 48 cells/m": {"n_grid": 48, "perturbation": None},
               "MPM floor (1e-4 m)": {"n_grid": 64, "perturbation": 1e-4}}
    main, more = headline_panels(labels, solvers)
    assert main == ["R-GNS 32x2", "GNS 32x4", "R-GNS 128x2 pretrained", "GNS 64x4 pretrained", "MPM 32 cells/m"]
    assert sorted(main + more) == sorted(labels)
    colours = _colours({"methods": dict.fromkeys(labels), "datasets": {"d": {"references": {"methods": solvers}}}})
    assert colours["R-GNS 32x2"] == colours["R-GNS 32x2, no hard walls"]  # a twin is its method's colour
    learned = [colours[label] for label in labels if label not in solvers and not label.endswith("walls")]
    assert len(set(learned)) == len(learned)  # every other method a colour of its own


@pytest.mark.parametrize("hard_walls,walls_off", [(None, True), (True, True), (True, "fresh")])
def test_seed_runs_are_aggregated_and_hard_walls_shown_both_ways(trained, tmp_path, monkeypatch, hard_walls, walls_off):
    """Three runs differing only by their seed get one row of mean and spread; a model that rolls
    out with hard walls is also scored without them (with ``without_hard_walls=fresh``, not a
    pretrained one); the farthest excursion out of the box is reported."""
    import rgns.evaluation.run as run_module
    from rgns.evaluation.methods import load_checkpoints, seed_groups

    checkpoint = next((trained / "sweep").glob("*/checkpoints/last.ckpt"))
    loaded = []
    for seed in range(3):
        method = load_checkpoints([checkpoint], "cpu")[0]
        method.label += f" (seed={seed})"
        method.info.update(seed=seed, overrides=["model=gns", f"seed={seed}"])
        with torch.no_grad():  # three different models
            for p in method.model.parameters():
                p.add_(1e-3 * seed)
        method.model.hard_walls = seed == 0
        method.info["pretrained"] = seed == 0
        loaded.append(method)
    assert list(seed_groups(loaded).values()) == [[m.label for m in loaded]]
    monkeypatch.setattr(run_module, "load_checkpoints", lambda paths, device, **_: loaded)
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"ckpt_path={checkpoint}", "task=forward", f"output_dir={tmp_path / 'out'}",
                                             "task.forward.steps=4", *FAST[:3],  # references on: none here, a note
                                             *([] if hard_walls is None else [f"hard_walls={str(hard_walls).lower()}"]),
                                             f"without_hard_walls={str(walls_off).lower()}"])
    results = evaluate(cfg)
    (name, sections), = results["datasets"].items()
    forward = sections["forward"]["methods"]
    twins = [m.label for m in loaded if f"{m.label}, no hard walls" in forward]
    # as trained: only the first rolls out with hard walls; hard_walls=true: all of them do; fresh: the first is pretrained
    expected = [loaded[0].label] if hard_walls is None else [m.label for m in loaded]
    assert twins == (expected if walls_off is True else expected[1:])
    assert all(row["max_outside"] is not None and row["max_outside"] >= 0 for row in forward.values())
    assert all(len(row["density_end_per_trajectory"]) == 2 for row in forward.values())
    group, = sections["over_seeds"].values()
    values = [forward[m.label]["rollout_mse"] for m in loaded]
    assert group["rollout_mse"]["values"] == pytest.approx(values)
    assert group["rollout_mse"]["mean"] == pytest.approx(np.mean(values))
    assert group["rollout_mse"]["std"] == pytest.approx(np.std(values, ddof=1))
    report = (tmp_path / "out" / "report.md").read_text()
    assert "### Over seeds on" in report and "(3 seeds)" in report and "Farthest outside the box" in report


def test_an_unknown_without_hard_walls_value_is_refused_before_any_work(tmp_path):
    """``without_hard_walls`` takes true, false or fresh; anything else is an error naming the
    value, raised before the run folder is made."""
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=["without_hard_walls=pretrained", f"output_dir={tmp_path / 'out'}"])
    with pytest.raises(ValueError, match="without_hard_walls='pretrained': true, false or fresh"):
        evaluate(cfg)
    assert not (tmp_path / "out").exists()


def test_the_evaluation_benchmark_compares_one_process_with_two(trained, capsys):
    """`python -m rgns.bench evaluation` times the same rollouts with 1 and 2 processes and
    checks that they agree."""
    from rgns.bench.evaluation import main as bench

    checkpoints = sorted(str(p) for p in (trained / "sweep").rglob("checkpoints/last.ckpt"))
    bench(["--checkpoints", *checkpoints, "--data-root", str(trained / "data"), "--trajectories", "2",
           "--steps", "5", "--no-references"])
    printed = capsys.readouterr().out
    assert "4 methods" in printed  # 2 checkpoints and 2 baselines (the tiny models have no hard walls: no twins)
    assert re.search(r"workers=1: [\d.]+ s", printed) and re.search(r"workers=2: [\d.]+ s", printed)
    assert "the same results: True" in printed
