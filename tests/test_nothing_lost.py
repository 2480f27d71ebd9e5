"""Nothing lost: every run of train.py ends with last.ckpt (whatever stopped it: max steps, max
time, SIGTERM, Ctrl-C), checkpoints are written whole, and runs never share a folder."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml

from rgns.runs import claim_run_dir
from rgns.training.checkpointing import AtomicCheckpointIO, LastCheckpoint

ROOT = Path(__file__).resolve().parents[1]
TINY = ["model.latent=16", "model.layers=2", "trainer=cpu", "trainer.log_every_n_steps=1",
        "trainer.val_check_interval=1000", "trainer.enable_progress_bar=false"]  # no validation in these runs


def command(dataset: Path, *overrides: str) -> list[str]:
    return [sys.executable, str(ROOT / "train.py"), "data=folder", f"data.root={dataset}", *TINY, *overrides]


def run(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")
    return subprocess.run(list(args), cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def step_of(path: Path) -> int:
    return torch.load(path, weights_only=False)["global_step"]


@pytest.mark.parametrize("stop", ["trainer.max_steps=7", "+trainer.max_time=00:00:00:04"])
def test_a_run_that_never_validated_ends_with_its_last_state(dataset, tmp_path, stop):
    overrides = [stop] if "max_steps" in stop else [stop, "trainer.max_steps=1000000"]
    done = run(tmp_path, *command(dataset, "data.num_workers=0", f"hydra.run.dir={tmp_path / 'run'}", *overrides))
    assert done.returncode == 0, done.stderr[-3000:]
    steps = json.loads((tmp_path / "run" / "timing.json").read_text())["steps"]
    assert steps > 0 and step_of(tmp_path / "run" / "checkpoints" / "last.ckpt") == steps
    assert not list((tmp_path / "run" / "checkpoints").glob("*.partial"))


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_at_a_step_saves_and_fails(dataset, tmp_path, signum):
    """SIGTERM to the process (a scheduler) or SIGINT to its whole group (Ctrl-C in a terminal,
    DataLoader worker included): the step finishes, last.ckpt holds it, the exit status is
    128 + signal, and resume= continues from it."""
    run_dir = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    process = subprocess.Popen(
        command(dataset, "data.num_workers=1", "trainer.max_steps=1000000", "callbacks.time_split.every_s=0.2",
                f"hydra.run.dir={run_dir}"),
        cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        for line in process.stderr:  # progress lines: training is under way
            if line.startswith("[train] step"):
                break
        else:
            pytest.fail("train.py ended before training started")
        time.sleep(1.0)
        if signum == signal.SIGINT:
            os.killpg(process.pid, signum)
        else:
            process.send_signal(signum)
        rest = process.stderr.read()
        process.wait(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 128 + signum, rest[-3000:]
    last = run_dir / "checkpoints" / "last.ckpt"
    assert f"stopped by {signal.Signals(signum).name}" in rest and str(last) in rest
    step = step_of(last)
    assert step > 0
    checkpoint = torch.load(last, weights_only=False)
    assert float(next(iter(checkpoint["optimizer_states"][0]["state"].values()))["step"]) == step  # a whole step

    resumed = run(tmp_path, *command(dataset, "data.num_workers=0", f"trainer.max_steps={step + 3}", f"resume={last}",
                                     f"hydra.run.dir={tmp_path / 'resumed'}"))
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert step_of(tmp_path / "resumed" / "checkpoints" / "last.ckpt") == step + 3


def test_a_kill_no_process_can_catch_loses_at_most_the_last_minutes(dataset, tmp_path):
    """SIGKILL (the machine taken away) leaves the last timed save: with every_minutes tiny,
    last.ckpt appears during training, whole, at a step where the ranks look at the clock."""
    run_dir = tmp_path / "run"
    last = run_dir / "checkpoints" / "last.ckpt"
    process = subprocess.Popen(
        command(dataset, "data.num_workers=0", "trainer.max_steps=1000000", "callbacks.last.every_minutes=0.001",
                f"hydra.run.dir={run_dir}"),
        cwd=tmp_path, env=dict(os.environ, OMP_NUM_THREADS="1"), stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while not last.exists() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert last.exists(), "no timed save of last.ckpt"
        time.sleep(1.0)
    finally:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(timeout=60)
    step = step_of(last)
    assert step > 0 and step % LastCheckpoint.CLOCK_EVERY == 0
    assert not list(last.parent.glob("*.partial"))


def test_last_checkpoint_refuses_a_period_that_is_not_positive():
    with pytest.raises(ValueError, match="every_minutes"):
        LastCheckpoint(every_minutes=0)


def test_runs_started_together_get_folders_of_their_own(dataset, tmp_path):
    """Two train.py runs launched at once, named by the same second (forced: the same base name),
    each write into a folder of their own, with their own seed in their own config."""
    base = "hydra.run.dir=${rgns_fresh:runs/together}"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    processes = [subprocess.Popen(command(dataset, "data.num_workers=0", "trainer.max_steps=3", f"seed={seed}", base),
                                  cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                 for seed in (1, 2)]
    for process in processes:
        _, err = process.communicate(timeout=600)
        assert process.returncode == 0, err[-3000:]
    folders = sorted((tmp_path / "runs").iterdir())
    assert [f.name for f in folders] == ["together", "together_2"]
    seeds = {yaml.safe_load((f / ".hydra" / "config.yaml").read_text())["seed"] for f in folders}
    assert seeds == {1, 2}
    for folder in folders:
        assert step_of(folder / "checkpoints" / "last.ckpt") == 3
        assert len(list((folder / "tensorboard").rglob("events.out.tfevents.*"))) == 1


def test_claim_run_dir_numbers_taken_names_and_answers_one_process_the_same(tmp_path):
    base = str(tmp_path / "runs" / "t")
    os.makedirs(base)  # taken by another run
    first = claim_run_dir(base)
    assert first == base + "_2" and os.path.isdir(first)
    assert claim_run_dir(base) == first  # the same process resolving its config again


class _Unpicklable:
    def __reduce__(self):
        raise RuntimeError("disk full")


def test_a_failed_checkpoint_write_leaves_the_previous_file(tmp_path):
    io = AtomicCheckpointIO()
    path = tmp_path / "last.ckpt"
    io.save_checkpoint({"global_step": 1}, path)
    before = path.read_bytes()
    with pytest.raises(RuntimeError, match="disk full"):
        io.save_checkpoint({"global_step": 2, "broken": _Unpicklable()}, path)
    assert path.read_bytes() == before and torch.load(path, weights_only=False)["global_step"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]
