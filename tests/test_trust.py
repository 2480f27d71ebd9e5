"""A checkpoint is data, not code; nothing written is overwritten; no mismatch is silent; a dead
DDP rank does not hang the run. Each case writes its bad input or plants its failure itself."""
from __future__ import annotations

import copy
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import make_metadata
from hydra.utils import instantiate
from test_inputs import (QUICK, config, evaluate_config, naming, trained,  # noqa: F401 (trained: a fixture)
                         write_checkpoint, write_dataset)

from rgns.data.contract import DatasetError, check_dataset, metadata_differences, read_metadata, write_metadata
from rgns.errors import ConfigError
from rgns.evaluation.plots import write_whole
from rgns.evaluation.run import evaluate
from rgns.inverse.goal import GoalSpec, target_points
from rgns.targets import UnsafeConfigError, check_checkpoint_configs
from rgns.training.average import average_checkpoints
from rgns.training.average import main as average_main
from rgns.training.module import CheckpointError, SimulatorModule, check_resume, load_simulator, warm_start

ROOT = Path(__file__).resolve().parents[1]
TINY = ["model.latent=16", "model.layers=2", "data.num_workers=0", "trainer=cpu", "trainer.enable_progress_bar=false"]


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def refusal(result: subprocess.CompletedProcess) -> list[str]:
    """The lines of a command's stderr from its ``error:`` line on (a refusal is one line, the last)."""
    lines = result.stderr.strip().splitlines()
    first = next((i for i, line in enumerate(lines) if line.startswith("error: ")), len(lines))
    return lines[first:]


def cause(error: BaseException, kind: type) -> BaseException:
    """``error``, or the cause of that kind Hydra's ``instantiate`` wrapped it around."""
    while not isinstance(error, kind) and error.__cause__ is not None:
        error = error.__cause__
    return error


def run(script: str, cwd: Path, *overrides: str, timeout: int = 300, **popen) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run([sys.executable, str(ROOT / script), *overrides], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout, **popen)


# ---- 1. checkpoints as data ---------------------------------------------------------------------------

def hostile(trained: Path, marker: Path, where: str) -> Path:
    """``trained`` with a ``_target_`` that writes ``marker`` (``numpy.savetxt``) planted at ``where``."""
    checkpoint = torch.load(trained, weights_only=True)
    hparams = checkpoint["hyper_parameters"]
    writer = {"_target_": "numpy.savetxt", "fname": str(marker), "X": [1.0]}
    if where == "model":
        hparams["model"] = dict(hparams["model"], _target_="numpy.savetxt", fname=str(marker), X=[1.0])
    elif where in ("loss", "optimizer", "scheduler"):
        hparams[where] = {**writer, "_partial_": where != "loss"}
    elif where == "nested":
        hparams["loss"] = dict(hparams["loss"], extra=writer)
    elif where == "generator":
        hparams["metadata"] = dict(hparams["metadata"], generator={"params": writer, "seed": 0})
    elif where == "other":
        hparams["pushforward"] = writer
    elif where == "interpolation":
        hparams["loss"] = dict(hparams["loss"], name="${rgns_fresh:" + str(marker) + "}")
    path = trained.with_name(f"hostile_{where}.ckpt")
    torch.save(checkpoint, path)
    return path


PLANTED = ["model", "loss", "optimizer", "scheduler", "nested", "generator", "other", "interpolation"]


@pytest.mark.parametrize("where", PLANTED)
def test_a_checkpoint_naming_foreign_code_is_refused_by_every_loader(trained, tmp_path, where):
    marker = tmp_path / "written_by_the_checkpoint"
    path = hostile(trained, marker, where)
    key = {"nested": "loss.extra", "generator": "metadata.generator.params", "other": "pushforward",
           "interpolation": "loss.name"}.get(where, where)
    expected = naming(str(path), f"hyper_parameters.{key}")
    with pytest.raises(CheckpointError, match=expected):
        load_simulator(str(path))
    module = SimulatorModule(**torch.load(trained, weights_only=True)["hyper_parameters"])
    with pytest.raises(CheckpointError, match=expected):
        warm_start(module, str(path))
    with pytest.raises(CheckpointError, match=expected):
        check_resume(module, str(path))
    with pytest.raises(CheckpointError, match=expected):
        average_checkpoints([str(trained), str(path)])
    assert not marker.exists()


def test_evaluate_refuses_a_foreign_target_in_one_line_and_writes_nothing(trained, tmp_path):
    marker = tmp_path / "written_by_the_checkpoint"
    path = hostile(trained, marker, "loss")
    result = run("evaluate.py", tmp_path, f"ckpt_path={path}", "baselines=null", "references=null", *QUICK)
    assert result.returncode == 1
    (line,) = refusal(result)
    assert line.startswith(f"error: {path}: hyper_parameters.loss._target_: 'numpy.savetxt'")
    assert not marker.exists()
    assert not (tmp_path / "evaluations").exists() or not any((tmp_path / "evaluations").iterdir())


def test_the_allow_list_keeps_rgns_own_targets():
    hparams = {"model": {"_target_": "rgns.models.RGNS", "latent": 8}, "loss": {"_target_": "rgns.training.losses.LossDesign"},
               "optimizer": {"_target_": "torch.optim.AdamW", "_partial_": True},
               "scheduler": {"_target_": "torch.optim.lr_scheduler.CosineAnnealingLR", "_partial_": True},
               "metadata": {"generator": {"params": {"_target_": "rgns.data.scenes.BodiesScene",
                                                     "solver": {"_target_": "rgns.physics.mpm.MPMSolver"}}}}}
    check_checkpoint_configs(hparams, "C")  # nothing raised
    for role, target in [("model", "rgns.data.generate.main"), ("optimizer", "torch.optim.swa_utils.AveragedModel"),
                         ("scheduler", "torch.optim.Adam"), ("model", "os.system")]:
        bad = copy.deepcopy(hparams)
        bad[role]["_target_"] = target
        with pytest.raises(UnsafeConfigError, match=naming(f"C: hyper_parameters.{role}._target_", target)):
            check_checkpoint_configs(bad, "C")


def test_a_dataset_naming_foreign_code_gets_no_solver_reference(tmp_path):
    from rgns.evaluation.references import SolverReferences
    from rgns.evaluation.tasks import Dataset

    marker = tmp_path / "written_by_the_dataset"
    root = write_dataset(tmp_path / "data")
    metadata = read_metadata(root)
    metadata["generator"] = {"seed": 0, "params": {"_target_": "numpy.savetxt", "fname": str(marker), "X": [1.0],
                                                   "solver": {"_target_": "rgns.physics.mpm.MPMSolver"}}}
    write_metadata(root, metadata)
    references, note = SolverReferences()(Dataset.load(str(root), "test", 1, 5, None))
    assert references == [] and "generator.params._target_: 'numpy.savetxt'" in note
    assert not marker.exists()


# ---- 2. nothing overwritten ------------------------------------------------------------------------

def test_training_into_a_folder_with_checkpoints_is_refused(dataset, tmp_path):
    folder = tmp_path / "run"
    common = ["data=folder", f"data.root={dataset}", "trainer.max_steps=4", "trainer.val_check_interval=4", *TINY,
              f"hydra.run.dir={folder}"]
    assert run("train.py", tmp_path, *common).returncode == 0
    last, config = folder / "checkpoints" / "last.ckpt", folder / ".hydra" / "config.yaml"
    before = digest(last), digest(config)
    result = run("train.py", tmp_path, *common, "seed=1")
    assert result.returncode == 1
    (line,) = refusal(result)
    assert line.startswith(f"error: {folder}: holds checkpoints of an earlier run (checkpoints/")
    assert "checkpoints/last.ckpt" in line and "overwrite=true" in line
    assert (digest(last), digest(config)) == before
    # resume= of that folder's own checkpoint goes on in it
    assert run("train.py", tmp_path, *common, "trainer.max_steps=6", f"resume={last}").returncode == 0
    assert torch.load(last, weights_only=True)["global_step"] == 6


def test_averaging_never_writes_over_an_input_or_an_existing_file(trained, tmp_path, capsys):
    other = write_checkpoint(tmp_path / "b.ckpt", tmp_path / "data")
    third = write_checkpoint(tmp_path / "c.ckpt", tmp_path / "data")
    before = digest(trained)
    for argv in ([str(trained), str(other), str(third)], [str(other), str(trained), str(other)]):  # output forgotten
        with pytest.raises(SystemExit) as stop:
            average_main(argv)
        assert stop.value.code == 2
        assert str(argv[0]) in capsys.readouterr().err
    assert digest(trained) == before
    out = tmp_path / "mean.ckpt"
    assert average_main([str(out), str(other), str(third)]) == 0
    assert average_main([str(out), str(other), str(third), "--overwrite"]) == 0


def test_a_second_evaluation_into_one_folder_is_refused_and_overwrite_clears_the_first(trained, tmp_path):
    folder = tmp_path / "eval"
    common = [f"ckpt_path={trained}", "baselines=null", "references=null", *QUICK, f"hydra.run.dir={folder}"]
    assert run("evaluate.py", tmp_path, *common).returncode == 0
    files = {p: digest(p) for p in folder.rglob("*") if p.is_file()}
    assert folder / "results.json" in files and not (folder / "INCOMPLETE").exists()
    result = run("evaluate.py", tmp_path, *common, "trajectories=1")
    assert result.returncode == 1 and "an earlier evaluation's files" in result.stderr and str(folder) in result.stderr
    assert {p: digest(p) for p in folder.rglob("*") if p.is_file()} == files  # .hydra included
    (folder / "stray.gif").write_bytes(b"GIF89a")  # what a different evaluation would have left
    assert run("evaluate.py", tmp_path, *common, "trajectories=1", "overwrite=true").returncode == 0
    assert not (folder / "stray.gif").exists()
    assert json.loads((folder / "results.json").read_text())["config"]["trajectories"] == 1


def test_sigterm_to_an_evaluation_says_so_and_marks_its_folder_incomplete(trained, tmp_path):
    folder = tmp_path / "eval"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    command = [sys.executable, str(ROOT / "evaluate.py"), f"ckpt_path={trained}", "baselines=null", "references=null",
               "task=forward", "task.forward.steps=12", "trajectories=null", f"hydra.run.dir={folder}"]
    process = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (folder / "INCOMPLETE").exists() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 143, err
    assert "evaluate.py stopped by SIGTERM" in err and str(folder) in err
    assert (folder / "INCOMPLETE").exists() and not (folder / "report.md").exists()


@pytest.mark.parametrize("interrupted", ["swallowed", "turned into another error"])
def test_a_signal_ends_its_block_as_stopped_whatever_the_interrupted_code_does(interrupted):
    from rgns.runs import Stopped, signals_stop, stop_received

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Stopped) as stopped:
        with signals_stop():
            try:
                os.kill(os.getpid(), signal.SIGTERM)  # the handler raises here, in the interrupted code
                time.sleep(5)
            except BaseException:
                assert stop_received() == signal.SIGTERM  # what the code inside asks before saying it finished
                if interrupted != "swallowed":
                    raise KeyError("half-changed state")
    assert stopped.value.signum == signal.SIGTERM and stop_received() is None
    assert signal.getsignal(signal.SIGTERM) is before  # the handler from before is back


def test_an_evaluation_whose_signal_was_swallowed_writes_nothing_after_it(trained, tmp_path, monkeypatch):
    """Python prints and drops an exception raised in a ``__del__`` or a weakref callback: a signal
    handled there leaves the evaluation running, which must then stop before its first output."""
    import rgns.evaluation.run as run_module
    from rgns.runs import Stopped, signals_stop

    def swallowing(*args, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        except BaseException:  # what a __del__ does with it
            pass
        return []

    monkeypatch.setattr(run_module, "build_baselines", swallowing)
    cfg = evaluate_config(tmp_path, f"ckpt_path={trained}", *QUICK)
    with pytest.raises(Stopped), signals_stop():
        evaluate(cfg)
    out = Path(cfg.output_dir)
    assert (out / "INCOMPLETE").exists()
    assert not (out / "results.json").exists() and not (out / "report.md").exists()


def test_a_failed_write_names_the_file_and_leaves_nothing(tmp_path, monkeypatch):
    path = tmp_path / "forward.gif"
    path.write_bytes(b"old")

    def full_disk(self, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full_disk)
    with pytest.raises(OSError, match=naming(str(path), "could not be written", "No space left on device")):
        write_whole(path, b"GIF89a...")
    monkeypatch.undo()
    assert path.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["forward.gif"]


# ---- 3. mismatches named -----------------------------------------------------------------------------

def test_metadata_differences_name_each_key():
    trained = make_metadata()
    assert metadata_differences(trained, copy.deepcopy(trained)) == []
    nudged = dict(trained, vel_std=[1.05e-3, 1e-3])  # within 10 % of the std
    assert metadata_differences(trained, nudged) == []
    other = dict(trained, default_connectivity_radius=0.1, dt=0.005, bounds=[[0.0, 1.0]] * 2, acc_mean=[0.0, 5e-5])
    said = " | ".join(metadata_differences(trained, other))
    for key in ("'default_connectivity_radius' 0.08 (trained) against 0.1", "'dt'", "'bounds'", "'acc_mean'"):
        assert key in said
    assert "'vel_std'" not in said


def test_evaluating_on_another_radius_warns_in_results_and_report(trained, tmp_path):
    other = write_dataset(tmp_path / "wide")
    metadata = read_metadata(other)
    write_metadata(other, dict(metadata, default_connectivity_radius=0.1))
    evaluate(evaluate_config(tmp_path, f"ckpt_path={trained}", f"data_root={other}", *QUICK))
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    (warning,) = results["warnings"]
    assert warning.startswith(str(trained)) and "'default_connectivity_radius' 0.08 (trained) against 0.1" in warning
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Warnings" in report and "'default_connectivity_radius'" in report


def test_resume_refuses_another_dataset_another_model_and_an_unreadable_file(trained, tmp_path):
    hparams = torch.load(trained, weights_only=True)["hyper_parameters"]
    other_data = dict(hparams, metadata=dict(hparams["metadata"], default_connectivity_radius=0.1))
    with pytest.raises(CheckpointError, match=naming(str(trained), "trained on other data than this run's",
                                                     "'default_connectivity_radius'", "init_from=")):
        check_resume(SimulatorModule(**other_data), str(trained))
    wider = dict(hparams, model=dict(hparams["model"], latent=16))
    with pytest.raises(CheckpointError, match=naming(str(trained), "model.latent: 8 in the checkpoint, 16 here")):
        check_resume(SimulatorModule(**wider), str(trained))
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(trained.read_bytes()[:2000])
    with pytest.raises(CheckpointError, match=naming(str(truncated), "not a readable checkpoint")):
        check_resume(SimulatorModule(**hparams), str(truncated))


def test_init_from_on_other_data_warns_by_key(trained, caplog):
    hparams = torch.load(trained, weights_only=True)["hyper_parameters"]
    module = SimulatorModule(**dict(hparams, metadata=dict(hparams["metadata"], dt=0.005)))
    warm_start(module, str(trained))
    assert f"{trained}: trained on other data than this run's: 'dt' 0.0025 (trained) against 0.005" in caplog.text


def test_resume_with_a_truncated_file_is_one_line_and_leaves_no_run_folder(dataset, tmp_path):
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(b"PK\x03\x04 not a whole checkpoint")
    result = run("train.py", tmp_path, "data=folder", f"data.root={dataset}", *TINY, f"resume={truncated}")
    assert result.returncode == 1
    (line,) = refusal(result)
    assert line.startswith(f"error: {truncated}: not a readable checkpoint")
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_positions_far_outside_the_bounds_are_refused(tmp_path):
    root = write_dataset(tmp_path / "data")
    write_metadata(root, dict(make_metadata(), bounds=[[10.0, 10.9], [0.1, 0.9]]))
    with pytest.raises(DatasetError, match=naming("train.h5, trajectory '00000'", "leaves the metadata's 'bounds'",
                                                  "axis 0")):
        check_dataset(root)


# ---- 5. unclear errors made clear ---------------------------------------------------------------------

@pytest.mark.parametrize("override, message", [
    ("model.layers=two", "model.layers='two': must be an integer of at least 1"),
    ("model.latent=3", "model.latent=3: R-GNS splits the latent into two halves"),
])
def test_model_sizes_name_the_key(tiny_dataset, override, message):
    cfg = config("train", ["data=folder", f"data.root={tiny_dataset}", override])
    with pytest.raises(Exception) as caught:  # raised inside Hydra's instantiate, which wraps it
        instantiate(cfg.module, model=cfg.model, loss=cfg.loss, metadata=make_metadata(), _recursive_=False)
    error = cause(caught.value, ConfigError)
    assert isinstance(error, ConfigError) and message in str(error)


def test_a_bad_size_on_the_command_line_is_one_line(dataset, tmp_path):
    result = run("train.py", tmp_path, "data=folder", f"data.root={dataset}", *TINY, "model.layers=two")
    assert result.returncode == 1
    assert refusal(result) == ["error: model.layers='two': must be an integer of at least 1"]


def test_zero_velocity_statistics_without_noise_name_the_key():
    metadata = dict(make_metadata(), vel_std=[0.0, 0.0])
    with pytest.raises(Exception) as caught:
        SimulatorModule(model={"_target_": "rgns.models.GNS", "latent": 8, "layers": 1}, metadata=metadata,
                        loss={"_target_": "rgns.training.losses.LossDesign"}, optimizer={}, noise_std=0.0)
    error = cause(caught.value, ConfigError)
    assert isinstance(error, ConfigError) and "metadata 'vel_std' is [0.0, 0.0] and noise_std=0.0" in str(error)


def test_goal_points_with_nan_name_the_file(tmp_path):
    path = tmp_path / "target.npy"
    np.save(path, np.array([[0.2, 0.2], [np.nan, 0.3]]))
    with pytest.raises(ValueError, match=naming(str(path), "NaN or Inf (first in row 1)")):
        target_points(GoalSpec(points=str(path)), [[0.1, 0.9], [0.1, 0.9]], 0.01, 2)


# ---- 4. no silent hang --------------------------------------------------------------------------------

def children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds the rank's process through /proc")
def test_a_killed_ddp_rank_ends_the_run_within_seconds_naming_the_rank(dataset, tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    command = [sys.executable, str(ROOT / "train.py"), "trainer=ddp_sim", "data=folder", f"data.root={dataset}",
               "model.latent=16", "model.layers=2", "data.num_workers=0", "trainer.max_steps=1000000",
               "trainer.val_check_interval=2", "trainer.enable_progress_bar=false", f"hydra.run.dir={tmp_path / 'run'}"]
    process = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)
    try:
        for line in process.stdout:  # both ranks are in the fit once a validation has run
            if line.startswith("[validation]"):
                break
        (rank1,) = [pid for pid in children(process.pid) if "train.py" in Path(f"/proc/{pid}/cmdline").read_text()]
        os.kill(rank1, signal.SIGKILL)
        killed = time.monotonic()
        err, _ = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 1 and time.monotonic() - killed < 30
    assert f"DDP rank 1 (pid {rank1}) was killed by SIGKILL" in err, err


@pytest.mark.parametrize("tool", ["tasks", "goal"])
def test_the_inverse_tools_refuse_an_out_folder_holding_files(trained, tmp_path, capsys, tool):
    from rgns.inverse.goal import main as goal_main
    from rgns.inverse.tasks import main as tasks_main

    out = tmp_path / "out"
    out.mkdir()
    (out / "inverse_comparison.json").write_text("{}")
    argv = ["--ckpt", str(trained), "--out", str(out)] + (["--text", "L"] if tool == "goal" else [])
    with pytest.raises(SystemExit) as stop:
        (goal_main if tool == "goal" else tasks_main)(argv)
    assert stop.value.code == 2
    assert f"--out {out}: holds files already" in capsys.readouterr().err
    assert (out / "inverse_comparison.json").read_text() == "{}"
