"""Inputs checked before work starts, nothing dropped without a word, checkpoints checked on load:
each bad input is written here, and must be refused (or, where the user asked for several things,
left out with a warning) with a message naming the file, key or option and what is wrong."""
from __future__ import annotations

import json
import logging
import os
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import lightning as L
import numpy as np
import pytest
import torch
from conftest import make_metadata, random_trajectory
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

import rgns.data.generate as generate
from rgns import config_dir
from rgns.data.contract import KINEMATIC, SAND, SPLITS, DatasetError, write_metadata, write_split
from rgns.data.datamodule import ParticleDataModule
from rgns.evaluation.methods import find_checkpoints, load_checkpoints
from rgns.evaluation.run import evaluate
from rgns.evaluation.tasks import Dataset, InverseConsistency
from rgns.inverse import tasks as inverse_tasks
from rgns.inverse.goal import main as goal_main
from rgns.training.module import CheckpointError, SimulatorModule, load_simulator

ROOT = Path(__file__).resolve().parents[1]

# evaluations that do little once their inputs pass: the checks under test run before any task
COMMON = ["baselines=null", "references=null", "animation.max_frames=2"]
FORWARD = ["task=forward", "task.forward.distribution_steps=[1]", "task.efficiency.repeats=1", "task.efficiency.memory=false"]
QUICK = [*FORWARD, "task.forward.steps=3"]


def naming(*parts: str) -> str:
    """A ``match`` pattern: every part, literally and in order."""
    return ".*".join(re.escape(part) for part in parts)


def write_dataset(folder: Path, dim: int = 2, frames: int = 20, counts=(2, 1, 1), types=None) -> Path:
    """A tiny dataset; ``types`` replaces the water particles' type (kinematic ones stay)."""
    rng = np.random.default_rng(0)
    for split, count in zip(SPLITS, counts):
        trajectories = [random_trajectory(rng, frames=frames, particles=30, dim=dim) for _ in range(count)]
        if types is not None:
            for _, particle_type in trajectories:
                particle_type[particle_type != KINEMATIC] = types
        write_split(folder / f"{split}.h5", trajectories)
    write_metadata(folder, make_metadata(dim=dim, frames=frames))
    return folder


def edit_metadata(folder: Path, **changes) -> Path:
    path = folder / "metadata.json"
    path.write_text(json.dumps(dict(json.loads(path.read_text()), **changes)))
    return path


def write_checkpoint(path: Path, root: Path, **stored) -> Path:
    """A GNS 8x1 checkpoint as train.py writes one (untrained: only what is stored matters here),
    with ``stored`` replacing or adding to what it records beside the weights."""
    datamodule = ParticleDataModule(str(root))
    datamodule.prepare_data()
    module = SimulatorModule(model={"_target_": "rgns.models.GNS", "latent": 8, "layers": 1},
                             metadata=datamodule.metadata, loss={"_target_": "rgns.training.losses.LossDesign", "mse": 1.0},
                             optimizer={"_target_": "torch.optim.Adam", "_partial_": True})
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams), "global_step": 0,
                "pytorch-lightning_version": L.__version__, "data_root": str(root.resolve()), **stored}, path)
    return path


@pytest.fixture
def trained(tmp_path) -> Path:
    """A checkpoint of water and boundary particles in 2D, beside its dataset."""
    return write_checkpoint(tmp_path / "run" / "checkpoints" / "last.ckpt", write_dataset(tmp_path / "data"))


def config(name: str, overrides: list[str]):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose(name, overrides=overrides)


def evaluate_config(tmp_path: Path, *overrides: str):
    return config("evaluate", [*COMMON, f"output_dir={tmp_path / 'out'}", *overrides])


def train_datamodule(overrides: list[str]) -> ParticleDataModule:
    """What train.py does with the data before the module is built."""
    datamodule = instantiate(config("train", overrides).data)
    datamodule.prepare_data()
    datamodule.metadata
    return datamodule


# ---- 3. the dataset, checked when training starts -------------------------------------------------

@pytest.mark.parametrize("key, value, expected", [
    ("default_connectivity_radius", "0.015", "a positive number"),
    ("dt", 0, "a positive number"),
    ("sequence_length", 19.5, "a positive integer"),
    ("dim", 2.0, "2 or 3"),
    ("vel_std", [1e-3, -1e-3], "a list of 2 numbers >= 0"),
    ("acc_mean", ["0", 0.0], "a list of 2 finite numbers"),
    ("bounds", [[0.9, 0.1], [0.1, 0.9]], "low < high"),
    ("num_particles_max", -1, "a positive integer"),
])
def test_metadata_values_of_the_wrong_type_or_range_name_the_key(tiny_dataset, key, value, expected):
    path = edit_metadata(tiny_dataset, **{key: value})
    with pytest.raises(DatasetError, match=naming(str(path), f"key '{key}'", expected)):
        train_datamodule(["data=folder", f"data.root={tiny_dataset}"])


@pytest.mark.parametrize("case, file, message", [
    ("nan_in_valid", "valid.h5", ", trajectory '00001': 'position' holds NaN or Inf (first at frame 7)"),
    ("empty_train", "train.h5", ": no trajectories; nothing to train on"),
    ("no_moving_particles", "train.h5", ", trajectory '00000': no moving particles"),
    ("unknown_particle_type", "test.h5", ", trajectory '00000': 'particle_type' holds [12]"),
    ("missing_test_split", "test.h5", ": split 'test' is missing"),
])
def test_every_split_is_checked_before_the_first_training_step(tiny_dataset, case, file, message):
    rng = np.random.default_rng(1)
    if case == "nan_in_valid":  # today reported only at the first validation, after training steps
        bad = random_trajectory(rng)
        bad[0][7, 3] = np.nan
        write_split(tiny_dataset / "valid.h5", [random_trajectory(rng), bad])
    elif case == "empty_train":
        write_split(tiny_dataset / "train.h5", [])
    elif case == "no_moving_particles":  # every particle kinematic: a NaN loss blamed on the learning rate
        position, particle_type = random_trajectory(rng, kinematic=60)
        write_split(tiny_dataset / "train.h5", [(position, particle_type), random_trajectory(rng)])
    elif case == "unknown_particle_type":  # no row of the models' type embedding
        position, particle_type = random_trajectory(rng)
        particle_type[0] = 12
        write_split(tiny_dataset / "test.h5", [(position, particle_type)])
    else:
        (tiny_dataset / "test.h5").unlink()
    with pytest.raises(DatasetError, match=re.escape(f"{tiny_dataset / file}{message}")):
        ParticleDataModule(str(tiny_dataset)).prepare_data()


def test_an_empty_valid_split_is_said_not_silent(tiny_dataset, caplog):
    write_split(tiny_dataset / "valid.h5", [])
    with caplog.at_level(logging.WARNING):
        ParticleDataModule(str(tiny_dataset)).prepare_data()
    assert any(f"{tiny_dataset / 'valid.h5'}: no trajectories: training runs without validation" in r.getMessage()
               for r in caplog.records)


def test_training_windows_longer_than_the_trajectories_are_refused_up_front(tiny_dataset):
    """data.lead=15 (pushforward) needs 5 + 1 + 15 + 1 frames; the trajectories have 20."""
    with pytest.raises(DatasetError, match=naming("train.h5", "20 frames, fewer than the 22")):
        ParticleDataModule(str(tiny_dataset), lead=15).prepare_data()


@pytest.mark.parametrize("override, message", [("history=0", "history=0"), ("noise_std=-1", "noise_std=-1"),
                                               ("data.batch_size=0", "data.batch_size=0")])
def test_training_options_out_of_range_name_the_option(tiny_dataset, override, message):
    with pytest.raises(Exception, match=re.escape(message)):
        train_datamodule(["data=folder", f"data.root={tiny_dataset}", override])


def test_a_missing_root_is_generated_only_where_the_default_dataset_lives(tiny_dataset, tmp_path, monkeypatch):
    """`data.root=<typo>` is an error naming it; the configured default roots (conf/data/waterdrop_small,
    experiment=main) are still generated on first use."""
    made = []

    def make(out_dir, **settings):
        made.append(out_dir)
        Path(out_dir).mkdir(parents=True)
        for name in ("metadata.json", *(f"{split}.h5" for split in SPLITS)):
            shutil.copy(tiny_dataset / name, Path(out_dir) / name)

    monkeypatch.setattr(generate, "generate_dataset", make)
    monkeypatch.chdir((tmp_path / "work").mkdir() or tmp_path / "work")
    typo = tmp_path / "work" / "datasets" / "waterdorp40_small"
    with pytest.raises(DatasetError, match=naming(str(typo), "no dataset here", "datasets/waterdrop40_small",
                                                  "data.make_root", "rgns.data.generate")):
        train_datamodule([f"data.root={typo}"])
    assert made == [] and not typo.exists()
    assert train_datamodule([]).metadata["dim"] == 2
    assert train_datamodule(["experiment=main"]).metadata["dim"] == 2
    assert made == ["datasets/waterdrop40_small", "datasets/waterdrop40_main"]
    assert train_datamodule([f"data.root={typo}", f"data.make_root={typo}"]).metadata["dim"] == 2  # asked for


def tiny_scene() -> dict:
    scene = generate.scene_config("waterdrop")
    scene["splits"] = {"train": 1, "valid": 1, "test": 1}
    return scene


@pytest.mark.parametrize("stray", ["train.h5", "metadata.json", ".parts/plan.json"])
def test_generation_refuses_a_folder_it_cannot_trust(tmp_path, stray):
    """Split files from other settings without metadata.json (they would be kept beside new
    metadata that contradicts them), or a corrupt metadata.json or plan: an error, nothing written."""
    out = tmp_path / "out"
    if stray == "train.h5":
        write_split(out / "train.h5", [random_trajectory(np.random.default_rng(0))])
        expected = naming(str(out), "holds train.h5 but no metadata.json")
    else:
        (out / stray).parent.mkdir(parents=True, exist_ok=True)
        (out / stray).write_text('{"generator": ')
        expected = naming(str(out / stray), "not valid JSON")
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    with pytest.raises(DatasetError, match=expected):
        generate.generate_dataset(tiny_scene(), out, num_frames=8, workers=1, progress=False)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


# ---- 3. the evaluation's inputs and options ---------------------------------------------------------

@pytest.mark.parametrize("overrides, message", [
    ([*QUICK, "trajectories=0"], "trajectories=0"),
    (["task=goal", "goal.steps=0"], "goal.steps=0"),
    ([*FORWARD, "task.forward.steps=0"], "task.forward.steps=0"),
    (["task=inverse", "task.inverse.horizons=[0,5]"], "task.inverse.horizons=[0, 5]"),
    ([*QUICK, "start=19"], "test.h5: trajectories [0] have no frame after t0 = 19 (start"),
])
def test_evaluation_options_out_of_range_name_the_option(trained, tmp_path, overrides, message):
    with pytest.raises(Exception, match=re.escape(message)):
        evaluate(evaluate_config(tmp_path, f"ckpt_path={trained}", *overrides))


def test_evaluation_reads_its_whole_split_first(trained, tmp_path):
    """trajectories=1 evaluates the first; a NaN in the second is still reported before any task."""
    rng = np.random.default_rng(2)
    bad = random_trajectory(rng, particles=30)
    bad[0][4, 0] = np.inf
    write_split(tmp_path / "data" / "test.h5", [random_trajectory(rng, particles=30), bad])
    cfg = evaluate_config(tmp_path, f"ckpt_path={trained}", *QUICK, "trajectories=1")
    with pytest.raises(DatasetError, match=naming(str(tmp_path / "data" / "test.h5"), "'00001'", "NaN or Inf")):
        evaluate(cfg)
    assert not (tmp_path / "out" / "results.json").exists()


# ---- 4. nothing dropped without a word --------------------------------------------------------------

def test_checkpoint_best_where_a_run_has_only_last_says_what_it_found(trained, tmp_path):
    with pytest.raises(FileNotFoundError, match=naming("checkpoint=best: no best*.ckpt", str(trained.parent),
                                                       "holds only last.ckpt", "checkpoint=last")):
        find_checkpoints(checkpoints_dir=str(tmp_path), checkpoint="best")
    with pytest.raises(ValueError, match=naming("checkpoint='newest'", "'last'", "'best'")):
        find_checkpoints(checkpoints_dir=str(tmp_path), checkpoint="newest")


def test_an_unreadable_checkpoint_is_named_and_the_others_evaluated(trained, tmp_path, caplog):
    broken = tmp_path / "broken_run" / "checkpoints" / "last.ckpt"
    broken.parent.mkdir(parents=True)
    broken.write_bytes(trained.read_bytes()[:1000])  # an interrupted copy
    cfg = evaluate_config(tmp_path, f"checkpoints_dir={tmp_path}", *QUICK)
    with caplog.at_level(logging.WARNING):
        results = evaluate(cfg)
    assert [m["source"] for m in results["methods"].values()] == [str(trained.resolve())]
    assert any(str(broken.resolve()) in r.getMessage() and "not a readable checkpoint" in r.getMessage()
               for r in caplog.records)
    (entry,) = results["not_evaluated"]  # also in results.json and the report, not only in evaluate.log
    assert entry.startswith(f"{broken.resolve()}: not a readable checkpoint")
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Not evaluated\n\nAsked for, but left out" in report and f"- {entry}" in report


def test_a_run_without_the_checkpoint_asked_for_is_listed_in_results_and_report(trained, tmp_path):
    best = tmp_path / "run_b" / "checkpoints" / "best-step5.ckpt"
    best.parent.mkdir(parents=True)
    shutil.copy(trained, best)
    results = evaluate(evaluate_config(tmp_path, f"checkpoints_dir={tmp_path}", "checkpoint=best", *QUICK))
    assert [m["source"] for m in results["methods"].values()] == [str(best.resolve())]
    assert results["not_evaluated"] == [f"{trained.parent} holds only last.ckpt, no best*.ckpt (checkpoint=best)"]
    assert f"- {results['not_evaluated'][0]}" in (tmp_path / "out" / "report.md").read_text()


def test_inverse_horizons_that_do_not_fit_are_listed_not_silently_dropped(trained, caplog):
    position, particle_type = (torch.from_numpy(a) for a in random_trajectory(np.random.default_rng(3)))
    dataset = Dataset("tiny", "", make_metadata(), [(position, particle_type)], start=5)
    method = load_checkpoints([trained])[0]
    with caplog.at_level(logging.WARNING):
        results, _ = InverseConsistency(horizons=[1, 100])([method], dataset)
        compared = inverse_tasks.compare_inverse({"GNS": method.model}, make_metadata(), [(position, particle_type)], [1, 100],
                                                 optimisers={})
    for settings in (results["settings"], compared["settings"]):
        assert settings["horizons"] == [1] and list(settings["dropped_horizons"]) == [100]
        assert "longer than the 14 frames after t0 = 5" in settings["dropped_horizons"][100]
    assert sum("K = 100 dropped" in r.getMessage() for r in caplog.records) == 2


def run_cli(main, argv: list[str], capsys) -> str:
    """The error an argparse command line exits with (status 2), as it prints it."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("extra, message", [
    (["--horizons", "1", "100"], "--horizons 100: the first 1 test trajectories of"),
    (["--label", "A"], "1 --label for 2 --ckpt"),
    (["--optimisers", "adam"], "--optimisers adam: the kinds are sph, mpm and learned"),
    (["--optimisers", "mpm:1,x"], "--optimisers mpm:1,x: after 'mpm:' come horizons K"),
    (["--optimisers", "mpm:7"], "--optimisers mpm:7: K = [7] not among --horizons"),
    (["--trajectories", "0"], "--trajectories 0"),
    (["--horizons", "0", "5"], "--horizons 0 5"),
])
def test_inverse_command_line_mistakes_are_refused_with_the_option(trained, tmp_path, capsys, extra, message):
    argv = ["--ckpt", str(trained), "--ckpt", str(trained), "--label", "A", "--label", "B", "--optimisers",
            "--stability-steps", "0", "--out", str(tmp_path / "out"), "--horizons", "1", "5"]
    if extra[0] == "--label":  # the two labels above replaced by one
        argv = argv[:4] + argv[8:]
    error = run_cli(inverse_tasks.main, argv + extra, capsys)
    assert message in error
    if extra[-1] == "100":
        assert "have 20 frames, so from t0 = k = 5 the longest horizon is 14" in error
    assert not (tmp_path / "out").exists()


def test_goal_steps_zero_is_refused_on_the_command_line(trained, tmp_path, capsys):
    error = run_cli(goal_main, ["--ckpt", str(trained), "--text", "L", "--steps", "0", "--out", str(tmp_path / "o")],
                    capsys)
    assert "--steps 0" in error


# ---- 5. checkpoints checked on load -----------------------------------------------------------------

@pytest.mark.parametrize("kind, message", [
    ("truncated", "not a readable checkpoint"),
    ("text", "not a readable checkpoint"),
    ("empty", "not a readable checkpoint"),
    ("other_torch_file", "a PyTorch file, but not an rgns training checkpoint"),
])
def test_a_file_that_is_not_a_readable_checkpoint_is_named(trained, tmp_path, kind, message):
    path = tmp_path / f"{kind}.ckpt"
    if kind == "truncated":
        path.write_bytes(trained.read_bytes()[: trained.stat().st_size // 2])
    elif kind == "text":
        path.write_text("epoch,loss\n1,0.5\n")
    elif kind == "empty":
        path.write_bytes(b"")
    else:
        torch.save({"weights": torch.zeros(3)}, path)
    with pytest.raises(CheckpointError, match=naming(str(path), message)):
        load_simulator(str(path))
    with pytest.raises(CheckpointError, match=re.escape(str(path))):  # the only one asked for: an error
        load_checkpoints([path])


@pytest.mark.parametrize("case, message", [
    ("3d", "trained on 2D data, but {where} is 3D (metadata 'dim')"),
    ("sand", "trained on particle types [3, 5], but {where} also holds type(s) [6], which it never saw"),
])
def test_a_checkpoint_on_data_unlike_its_training_data_is_refused(trained, tmp_path, case, message):
    assert load_simulator(str(trained))[0].particle_types == [KINEMATIC, 5]  # recorded from the training split
    other = write_dataset(tmp_path / case, dim=3) if case == "3d" else write_dataset(tmp_path / case, types=SAND)
    cfg = evaluate_config(tmp_path, f"ckpt_path={trained}", f"data_root={other}", *QUICK)
    with pytest.raises(CheckpointError, match=naming(str(trained.resolve()),
                                                     message.format(where=other.resolve() / "test.h5"))):
        evaluate(cfg)


class RunsCode:
    """Unpickled, it makes the folder ``marker``: any code a hostile checkpoint chooses could run."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.mkdir, (str(self.marker),)


def test_a_checkpoint_holding_pickled_code_is_refused_without_running_it(trained, tmp_path):
    marker = tmp_path / "code_ran"
    torch.save(dict(torch.load(trained, weights_only=True), extra=RunsCode(marker)), trained)
    with pytest.raises(CheckpointError, match=naming(str(trained), "holds a pickled Python object", "not loaded")):
        load_simulator(str(trained))
    assert not marker.exists()


@pytest.mark.parametrize("name", ["rgns", "gns"])
def test_the_shipped_checkpoints_load_with_weights_only(name):
    model, extras = load_simulator(str(ROOT / "pretrained" / "waterdrop40_main" / f"{name}.ckpt"))
    assert extras["global_step"] > 0 and model.hard_walls
    assert extras["data_root_relative"] is None  # written before it was recorded: data_root=... as before


# ---- 6. a checkpoint's dataset, on another machine ----------------------------------------------------

def test_a_checkpoint_records_its_dataset_as_the_run_gave_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for root, relative in (("datasets/water", "datasets/water"), (str(tmp_path / "datasets" / "water"), None)):
        module = SimpleNamespace(trainer=SimpleNamespace(world_size=1, datamodule=SimpleNamespace(root=Path(root))))
        checkpoint = {}
        SimulatorModule.on_save_checkpoint(module, checkpoint)  # as the trainer calls it, on a stand-in module
        assert checkpoint["data_root"] == str((tmp_path / "datasets" / "water").resolve())
        assert checkpoint["data_root_relative"] == relative


def test_a_checkpoint_from_another_machine_finds_its_dataset_from_the_current_folder(tmp_path, monkeypatch, capsys):
    data = write_dataset(tmp_path / "datasets" / "water")
    gone = tmp_path / "another_machine" / "datasets" / "water"  # where it was trained
    moved = write_checkpoint(tmp_path / "run" / "checkpoints" / "last.ckpt", data, data_root=str(gone),
                             data_root_relative="datasets/water")
    monkeypatch.chdir(tmp_path)
    results = evaluate(evaluate_config(tmp_path, f"ckpt_path={moved}", *QUICK))
    assert [d["root"] for d in results["datasets"].values()] == [str(data.resolve())]
    error = run_cli(inverse_tasks.main, ["--ckpt", str(moved), "--horizons", "1", "100", "--out", str(tmp_path / "o")],
                    capsys)
    assert f"test trajectories of {data.resolve()} have 20 frames" in error
    older = write_checkpoint(tmp_path / "older" / "last.ckpt", data, data_root=str(gone))  # no data_root_relative
    with pytest.raises(DatasetError, match=re.escape(str(gone))):  # its recorded path, as before
        evaluate(evaluate_config(tmp_path, f"ckpt_path={older}", *QUICK))

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # neither path exists from here
    with pytest.raises(CheckpointError, match=naming(str(moved), f"neither at {gone}", "nor at",
                                                     str(elsewhere.resolve() / "datasets" / "water"), "data_root=")):
        evaluate(evaluate_config(tmp_path, f"ckpt_path={moved}", *QUICK))
