"""Staged recipes (rgns.training.stages, scripts/pretrain.sh): the shipped presets compose stage by
stage; a recipe chains its stages (each from the previous stage's checkpoint), a stopped stage goes on
from its last checkpoint, finished stages are skipped, and the result's provenance names no local path."""
from __future__ import annotations

import json
import math
import os
import signal
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
from omegaconf import OmegaConf

from rgns import config_dir
from rgns.data.contract import SPLITS, DatasetError, write_metadata, write_split
from rgns.training import stages
from rgns.training.stages import read_preset

ROOT = Path(__file__).resolve().parents[1]
PRESETS = sorted((config_dir() / "experiment" / "pretrain").glob("*.yaml"))

TINY = """# @package _global_
defaults:
  - override /data: folder
  - override /trainer: cpu
model: {latent: 16, layers: 2}
data: {num_workers: 0}
trainer: {log_every_n_steps: 1, enable_progress_bar: false, limit_val_batches: 2}
module: {val_rollout_steps: 5, val_consistency_steps: 2, val_trajectories: 1}
callbacks: {early_stopping: null}
pretrain:
  benchmark: tiny
  model: rgns
  stages:
    - name: first
      overrides: [trainer.max_steps=6, trainer.val_check_interval=3]
    - name: second   # a learning rate of 0: its weights stay those it started from
      overrides: [trainer.max_steps=60, trainer.val_check_interval=5, module.optimizer.lr=0.0, module.scheduler=null]
"""


def test_shipped_presets_compose_stage_by_stage(tmp_path):
    assert {p.stem for p in PRESETS} >= {"waterdrop_rgns", "waterdrop_gns"}
    for path in PRESETS:
        spec = read_preset(path)
        for stage in spec["stages"]:
            with initialize_config_dir(str(config_dir()), version_base="1.3"):
                cfg = compose("train", overrides=[f"output_dir={tmp_path}", f"experiment=pretrain/{path.stem}",
                                                  *stage["overrides"], "init_from=x.ckpt", "trainer=gpu"])
            assert cfg.model._target_ == {"rgns": "rgns.models.RGNS", "gns": "rgns.models.GNS"}[spec["model"]]
            assert cfg.trainer.max_time is None and cfg.trainer.accelerator == "gpu"
            assert cfg.callbacks.checkpoint.monitor == "val/rollout_mse"
        assert cfg.data.root == "datasets/waterdrop_train256"
        assert "out_dir=datasets/waterdrop_train256" in spec["dataset"]


def test_shipped_provenance_names_its_preset_and_no_local_path():
    for path in sorted((ROOT / "pretrained").rglob("*.json")):
        text = path.read_text()
        assert "outputs/s" not in text and '"init_from"' not in text and "/work/" not in text, path
    for model in ("rgns", "gns"):
        record = json.loads((ROOT / "pretrained" / "waterdrop40_main_64" / f"{model}.json").read_text())
        assert record["preset"] == f"conf/experiment/pretrain/waterdrop_{model}.yaml"
        stages = [s["name"] for s in read_preset(config_dir() / "experiment" / "pretrain" / f"waterdrop_{model}.yaml")["stages"]]
        assert [s["recipe_stage"] for s in record["stages"] if s.get("recipe_stage")] == stages


def recipe(tmp_path: Path, dataset: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "rgns.training.stages", f"preset={tmp_path / 'conf/experiment/pretrain/tiny.yaml'}",
            f"data.root={dataset}", f"out={tmp_path / 'out'}", f"run_dir={tmp_path / 'runs'}", *extra]


def weights(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)["state_dict"]


def test_recipe_chains_resumes_and_skips(dataset, tmp_path):
    (tmp_path / "conf/experiment/pretrain").mkdir(parents=True)
    (tmp_path / "conf/experiment/pretrain/tiny.yaml").write_text(TINY)
    env = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1", PYTHONWARNINGS="ignore")
    runs, out = tmp_path / "runs", tmp_path / "out"

    # 1. stopped during the second stage (SIGTERM to the runner, passed on to train.py)
    log = tmp_path / "first_try.log"
    with open(log, "w") as sink:  # a file, not a pipe that nobody reads while the test waits
        process = subprocess.Popen(recipe(tmp_path, dataset), cwd=tmp_path, env=env, stdout=sink,
                                   stderr=subprocess.STDOUT)
    last = runs / "second" / "checkpoints" / "last.ckpt"
    try:
        deadline = time.time() + 300
        while not last.is_file() and process.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=300)
    finally:
        process.kill()
    output = log.read_text()
    assert process.returncode == 143, output
    assert (runs / "first" / "done.json").is_file() and not (runs / "second" / "done.json").exists()
    stopped_at = torch.load(last, weights_only=True)["global_step"]
    assert 0 < stopped_at < 60
    first = json.loads((runs / "first" / "done.json").read_text())
    picked = runs / "first" / first["checkpoint"]
    assert first["pick"] == "best" and first["checkpoint"].startswith("checkpoints/best-step") and picked.is_file()
    # the second stage started from the first's pick
    started = OmegaConf.load(runs / "second" / ".hydra" / "overrides.yaml")
    assert f"init_from={picked}" in started and "seed=0" in started

    # 2. the same command: the first stage is skipped, the second goes on from its last.ckpt
    again = subprocess.run(recipe(tmp_path, dataset), cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=600)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "stage 1/2 first: done" in again.stdout and f"goes on from {last}" in again.stdout
    resumed = OmegaConf.load(runs / "second" / ".hydra" / "overrides.yaml")
    assert f"resume={last}" in resumed and "init_from=null" in resumed
    second = json.loads((runs / "second" / "done.json").read_text())
    assert second["last_step"] == 60 and second["sessions"] == 2
    # stage 2's weights are stage 1's pick (lr 0), and the final file is stage 2's pick
    final = out / "rgns.ckpt"
    assert (out / "rgns.ckpt").read_bytes() == (runs / "second" / second["checkpoint"]).read_bytes()
    before, after = weights(picked), weights(final)
    assert before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)

    record = json.loads((out / "rgns.json").read_text())
    assert record["preset"] == "tiny.yaml" and record["experiment"] == "pretrain/tiny" and record["seed"] == 0
    assert [s["name"] for s in record["stages"]] == ["first", "second"]
    assert record["stages"][0]["init_from"] is None
    assert record["stages"][1]["init_from"] == f"first: {picked.name}"
    assert record["stages"][1]["overrides"][-1] == "module.scheduler=null"
    assert record["overrides"] == ["data.root=<local>/" + dataset.name]
    assert record["global_step"] == second["global_step"] and record["monitor"] == "val/loss"
    assert isinstance(record["best_score"], float)
    assert str(tmp_path) not in (out / "rgns.json").read_text()
    assert sorted(p.name for p in out.iterdir()) == ["rgns.ckpt", "rgns.json"]  # no temporary file left

    # 3. once more: nothing runs
    logs = {p: p.stat().st_mtime_ns for p in runs.rglob("*")}
    third = subprocess.run(recipe(tmp_path, dataset), cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=300)
    assert third.returncode == 0, third.stdout + third.stderr
    assert third.stdout.count(": skipped") == 2 and "nothing to write" in third.stdout
    assert "train.py" not in third.stdout
    assert {p: p.stat().st_mtime_ns for p in runs.rglob("*")} == logs

    # other overrides on the same folders are refused, not mixed; another file at out= is kept
    other = subprocess.run(recipe(tmp_path, dataset, "trainer.max_steps=7"), cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=300)
    assert other.returncode == 2 and "other settings" in other.stderr
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "rgns.ckpt").write_bytes(b"another file")
    kept = subprocess.run(recipe(tmp_path, dataset, f"out={tmp_path / 'elsewhere'}"), cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert kept.returncode == 2 and "not overwritten" in kept.stderr
    assert (tmp_path / "elsewhere" / "rgns.ckpt").read_bytes() == b"another file"


# ---- strided presets: their windows fit the data, their lengths are the stride-1 recipe's in time ----

def stage_config(preset: Path, stage: dict, tmp_path: Path):
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose("train", overrides=[f"output_dir={tmp_path}", f"experiment=pretrain/{preset.stem}",
                                           *stage["overrides"], "init_from=x.ckpt"])


def preset_frames(spec: dict) -> int:
    """Frames per trajectory of a preset's dataset: its num_frames= argument, else its scene's."""
    arguments = dict(a.split("=", 1) for a in spec["dataset"])
    if "num_frames" in arguments:
        return int(arguments["num_frames"])
    return int(OmegaConf.load(config_dir() / "scene" / f"{arguments['scene']}.yaml").num_frames)


def dataset_of(root: Path, frames: int) -> Path:
    """One trajectory of ``frames`` frames in each split: the shapes the datamodule checks."""
    rng = np.random.default_rng(0)
    for split in SPLITS:
        write_split(root / f"{split}.h5", [random_trajectory(rng, frames=frames, particles=8, kinematic=2)])
    write_metadata(root, make_metadata(frames=frames))
    return root


def test_every_stage_of_every_preset_fits_its_trajectories(tmp_path):
    """Each stage's training windows (lead + history + 1 + horizon frames, counted without the early
    windows' filled-in lead), its pushes and unrolls, and its validation rollout fit one phase of the
    preset's trajectories at its stride, by the datamodule's own check on a dataset of that length."""
    strides = set()
    for path in PRESETS:
        spec = read_preset(path)
        frames = preset_frames(spec)
        root = tmp_path / f"frames{frames}"
        if not root.exists():
            dataset_of(root, frames)
        for stage in spec["stages"]:
            cfg = stage_config(path, stage, tmp_path)
            where = f"{path.name}, stage {stage['name']}"
            stride, lead, horizon, k = cfg.data.stride, cfg.data.lead, cfg.data.horizon, cfg.history
            strides.add(stride)
            phase = frames // stride  # frames in a trajectory's shortest phase
            data = instantiate(cfg.data, root=str(root), make=None, make_root=None, early_windows=False, num_workers=0)
            data.check()  # raises DatasetError when a window does not fit a phase
            assert lead + k + 1 + horizon <= phase, where
            pushforward, unroll = cfg.module.get("pushforward"), cfg.module.get("unroll")
            if pushforward:
                assert max(pushforward.unrolls) <= lead, where
            if unroll:
                assert max(unroll.lengths) <= horizon, where
            # the validation rollout runs its whole length from frame k of a phase
            assert cfg.module.val_rollout_steps <= phase - k - 1, where
            # the check is live: one frame more than the phase holds is refused
            too_long = instantiate(cfg.data, root=str(root), make=None, make_root=None, early_windows=False,
                                   num_workers=0, lead=phase - k - horizon)
            with pytest.raises(DatasetError, match="window needs"):
                too_long.check()
    assert strides >= {1, 2, 4}


def physical(cfg) -> dict:
    """A stage's settings counted in model steps (each spans data.stride frames)."""
    pushforward, unroll = cfg.module.get("pushforward"), cfg.module.get("unroll")
    return {"data.lead": [cfg.data.lead], "data.horizon": [cfg.data.horizon],
            "module.val_rollout_steps": [cfg.module.val_rollout_steps],
            "module.val_consistency_steps": [cfg.module.val_consistency_steps],
            "module.pushforward.unrolls": list(pushforward.unrolls) if pushforward else [],
            "module.unroll.lengths": list(unroll.lengths) if unroll else []}


def other_settings(cfg) -> dict:
    """What a stride leaves as it is: the model, the optimiser, the noise, the losses, the dataset, and
    everything counted in optimiser steps."""
    pushforward = cfg.module.get("pushforward")
    return {"model": OmegaConf.to_container(cfg.model), "optimizer": OmegaConf.to_container(cfg.module.optimizer),
            "scheduler": OmegaConf.to_container(cfg.module.scheduler), "noise_std": cfg.noise_std,
            "density_weight": cfg.get("density_weight"), "early_windows": cfg.data.early_windows,
            "root": cfg.data.root, "max_steps": cfg.trainer.max_steps,
            "val_check_interval": cfg.trainer.val_check_interval, "max_time": cfg.trainer.max_time,
            "pushforward": {k: list(pushforward[k]) for k in ("steps", "probs")} if pushforward else None,
            "unroll_steps": list(cfg.module.unroll.steps) if cfg.module.get("unroll") else None,
            "compile": cfg.module.compile, "val_trajectories": cfg.module.val_trajectories}


def test_strided_presets_take_the_stride_one_recipes_lengths_in_time(tmp_path):
    """A preset with data.stride = s that extends another (Hydra defaults) has its stages, stage by
    stage, with every length in model steps ceil(n / s) of the other's n, and all else the same."""
    strided = []
    for path in PRESETS:
        own = OmegaConf.load(path)
        stride = OmegaConf.select(own, "data.stride", default=1)
        if stride == 1:
            continue
        parents = [d for d in own.get("defaults", []) if isinstance(d, str) and d.startswith("/experiment/pretrain/")]
        assert len(parents) == 1, f"{path.name}: extends no stride-1 preset through its defaults"
        base = config_dir() / "experiment" / f"{parents[0].removeprefix('/experiment/')}.yaml"
        assert OmegaConf.select(OmegaConf.load(base), "data.stride", default=1) == 1
        spec, base_spec = read_preset(path), read_preset(base)
        assert len(spec["stages"]) == len(base_spec["stages"]), path.name
        assert {k: spec.get(k) for k in ("benchmark", "model", "dataset")} == \
               {k: base_spec.get(k) for k in ("benchmark", "model", "dataset")}
        for stage, base_stage in zip(spec["stages"], base_spec["stages"]):
            cfg, reference = stage_config(path, stage, tmp_path), stage_config(base, base_stage, tmp_path)
            assert cfg.data.stride == stride and reference.data.stride == 1
            expected = {key: [math.ceil(n / stride) for n in values] for key, values in physical(reference).items()}
            assert physical(cfg) == expected, f"{path.name}, stage {stage['name']}"
            assert other_settings(cfg) == other_settings(reference), f"{path.name}, stage {stage['name']}"
        strided.append(stride)
    assert sorted(strided) == [2, 2, 4]


def test_the_default_out_folder_is_the_presets(tmp_path, monkeypatch, capsys):
    """Without out=, a recipe writes to pretrained/<preset>_rebuilt: the stride-4 recipe neither
    refuses over the plain recipe's result nor would it overwrite it, and the plain recipe keeps its folder."""
    monkeypatch.chdir(tmp_path)
    plain = tmp_path / "pretrained" / "waterdrop_gns_rebuilt" / "gns.ckpt"
    plain.parent.mkdir(parents=True)
    plain.write_bytes(b"the plain recipe's result")
    common = [f"run_dir={tmp_path / 'runs'}", f"data.root={tmp_path / 'data'}"]  # data.root: nothing generated

    assert stages.main(["waterdrop", "gns", *common]) == 2
    assert "pretrained/waterdrop_gns_rebuilt/gns.ckpt exists" in capsys.readouterr().err

    started = []
    monkeypatch.setattr(stages, "run_logged", lambda command, log: started.append(command) or 1)
    assert stages.main(["waterdrop", "gns", "preset=waterdrop_gns_stride4", *common]) == 1  # the first stage's exit
    output = capsys.readouterr().out
    assert "result pretrained/waterdrop_gns_stride4_rebuilt/gns.ckpt" in output
    assert len(started) == 1 and "experiment=pretrain/waterdrop_gns_stride4" in started[0]
    assert plain.read_bytes() == b"the plain recipe's result"
