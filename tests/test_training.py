"""Smoke tests of train.py: sweeps over loss designs and ablations, DDP on two CPU ranks,
resume after a kill, and a non-finite loss. Each runs train.py as a user would."""
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
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from conftest import make_metadata
from rgns.models import State
from test_models import perturb, random_state
from rgns.training.module import CheckpointError, SimulatorModule, warm_start

ROOT = Path(__file__).resolve().parents[1]
TINY = ["model.latent=16", "model.layers=2", "data.num_workers=0", "trainer.log_every_n_steps=1"]
EMA = ("+callbacks.ema={_target_: lightning.pytorch.callbacks.WeightAveraging, "  # weight averaging, fast
       "multi_avg_fn: {_target_: torch.optim.swa_utils.get_ema_multi_avg_fn, decay: 0.5}}")


def train(cwd: Path, *overrides: str, check: bool = True, **popen) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")
    command = [sys.executable, str(ROOT / "train.py"), *overrides]
    return subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, check=check, timeout=600, **popen)


def scalar_tags(run: Path) -> set[str]:
    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    return set(events.Tags()["scalars"])


def sweep_runs(cwd: Path) -> list[Path]:
    (sweep,) = (cwd / "multirun").iterdir()
    return sorted(p for p in sweep.iterdir() if p.is_dir())


def test_loss_sweep_writes_one_run_per_design(dataset, tmp_path):
    train(tmp_path, "-m", "loss=dl1,dl2,dl3,dl4", "data=folder", f"data.root={dataset}", "trainer=cpu",
          "trainer.max_steps=20", "trainer.val_check_interval=10", *TINY)
    runs = sweep_runs(tmp_path)
    assert len(runs) == 4
    names = []
    for run in runs:
        assert (run / "checkpoints" / "last.ckpt").is_file()
        tags = scalar_tags(run)
        assert {"train/forward_mse", "train/inverse_mse", "val/loss", "val/rollout_mse", "val/consistency_mse"} <= tags
        names.append(torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["hyper_parameters"]["loss"]["name"])
    assert sorted(names) == ["DL1", "DL2", "DL3", "DL4"]
    assert "train/forward_mmd" in scalar_tags(runs[0]) and "train/forward_cosine" in scalar_tags(runs[1])


def test_default_data_is_generated_on_first_use(tmp_path):
    """`python train.py` on a fresh clone: the DataModule makes the default dataset inside the
    running Hydra app (the scene config is composed with Hydra too), at its data.make_root."""
    root = tmp_path / "datasets" / "waterdrop40_small"  # the default root, from the run's folder
    train(tmp_path, "+data.make.num_trajectories=1", "+data.make.num_frames=12",
          "data.make.workers=1", "trainer=cpu", "trainer.max_steps=2", "trainer.val_check_interval=2",
          "module.val_rollout_steps=3", "module.val_consistency_steps=2", *TINY)
    metadata = json.loads((root / "metadata.json").read_text())
    assert metadata["generator"]["scene"] == "waterdrop" and metadata["sequence_length"] == 11
    (run,) = (tmp_path / "runs").iterdir()
    assert (run / "checkpoints" / "last.ckpt").is_file()


def test_ablation_sweep_encoder_and_edges(dataset, tmp_path):
    train(tmp_path, "-m", "model.encoder=ilp,mlp", "model.edges=fixed,updated", "data=folder", f"data.root={dataset}",
          "trainer=cpu", "trainer.max_steps=10", "trainer.val_check_interval=10", *TINY)
    runs = sweep_runs(tmp_path)
    assert len(runs) == 4
    seen = set()
    for run in runs:
        model = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["hyper_parameters"]["model"]
        seen.add((model["encoder"], model["edges"]))
        assert {"train/forward_mse", "train/inverse_mse"} <= scalar_tags(run)
    assert seen == {("ilp", "fixed"), ("ilp", "updated"), ("mlp", "fixed"), ("mlp", "updated")}


def test_every_model_trains(dataset, tmp_path):
    train(tmp_path, "-m", "model=gns,sep_gns,rgns_forward_only", "data=folder", f"data.root={dataset}", "trainer=cpu",
          "trainer.max_steps=6", "trainer.val_check_interval=6", *TINY)
    runs = sweep_runs(tmp_path)
    assert len(runs) == 3
    tags = [scalar_tags(run) for run in runs]
    assert "train/inverse_mse" not in tags[0]  # GNS: forward only
    assert "train/inverse_mse" in tags[1]  # Sep-GNS trains its backward GNS in the same step
    assert "train/inverse_mse" not in tags[2] and "val/inverse_mse" in tags[2]  # R-GNS†


def test_ddp_sweep_runs_each_job_once_on_two_ranks(dataset, tmp_path):
    train(tmp_path, "-m", "loss=dl1,dl4", "trainer=ddp_sim", "trainer.max_steps=10", "trainer.val_check_interval=5",
          "data=folder", f"data.root={dataset}", *TINY)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["multirun"]  # no stray run folders
    runs = sweep_runs(tmp_path)
    assert [p.name for p in runs] == ["0", "1"]
    for run in runs:
        checkpoint = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
        assert checkpoint["world_size"] == 2
        assert checkpoint["global_step"] == 10
        assert (run / "train_ddp_process_1.log").is_file()  # rank 1 ran this job, in this folder


def test_last_checkpoint_is_the_latest_state(dataset, tmp_path):
    """last.ckpt follows training (resume point), best-step*.ckpt the monitored metric: with a
    metric that can never improve after the first validation, last.ckpt still reaches the end."""
    run = tmp_path / "run"
    train(tmp_path, "data=folder", f"data.root={dataset}", "trainer=cpu", "trainer.max_steps=12",
          "trainer.val_check_interval=4", "+callbacks.checkpoint.mode=max", "callbacks.early_stopping=null",
          f"hydra.run.dir={run}", *TINY)  # mode=max on a loss: the first validation stays the best
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == 12
    (best,) = (run / "checkpoints").glob("best-step*.ckpt")
    assert torch.load(best, weights_only=False)["global_step"] < 12
    # callbacks.time_split: the fit's time in optimisation steps and validation, in the run folder
    timing = json.loads((run / "timing.json").read_text())
    assert timing["steps"] == 12 and 0 < timing["steps_s"] < timing["fit_s"] and timing["validation_s"] > 0
    assert timing["steps_fraction"] == pytest.approx(timing["steps_s"] / timing["fit_s"])


def test_resume_after_kill_continues_from_last_checkpoint(dataset, tmp_path):
    run = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    command = [sys.executable, str(ROOT / "train.py"), "data=folder", f"data.root={dataset}", "trainer=cpu",
               "trainer.max_steps=100000", "trainer.val_check_interval=5", f"hydra.run.dir={run}", *TINY]
    process = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    last = run / "checkpoints" / "last.ckpt"
    try:
        deadline = time.time() + 300
        while time.time() < deadline:
            time.sleep(0.5)
            if last.is_file() and torch.load(last, weights_only=False)["global_step"] >= 10:
                break
        else:
            pytest.fail("no checkpoint at step 10 within 300 s")
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    killed = torch.load(last, weights_only=False)
    step = killed["global_step"]
    adam_step = float(next(iter(killed["optimizer_states"][0]["state"].values()))["step"])
    assert adam_step == step

    resumed_dir = tmp_path / "resumed"
    train(tmp_path, "data=folder", f"data.root={dataset}", "trainer=cpu", f"trainer.max_steps={step + 5}",
          "trainer.val_check_interval=5", f"resume={last}", f"hydra.run.dir={resumed_dir}", *TINY)
    resumed = torch.load(resumed_dir / "checkpoints" / "last.ckpt", weights_only=False)
    assert resumed["global_step"] == step + 5  # continued, did not start over
    # Adam's own step count continued too: its state came back with the weights
    assert float(next(iter(resumed["optimizer_states"][0]["state"].values()))["step"]) == step + 5
    # and the training windows went on in the killed run's order from where it was, not from its epoch's start
    (order,) = killed["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    assert order["position"] == 2 * killed["loops"]["fit_loop"]["epoch_loop.batch_progress"]["current"]["completed"]
    (order_after,) = resumed["loops"]["fit_loop"]["state_dict"]["combined_loader"]
    assert order_after == {"seed": order["seed"], "position": order["position"] + 2 * 5}


def test_init_from_starts_a_new_run_from_a_checkpoints_weights(dataset, tmp_path):
    common = ["data=folder", f"data.root={dataset}", "trainer=cpu", "trainer.val_check_interval=3",
              "callbacks.early_stopping=null", *TINY]
    train(tmp_path, *common, "trainer.max_steps=6", f"hydra.run.dir={tmp_path / 'first'}")
    first = tmp_path / "first" / "checkpoints" / "last.ckpt"
    # a learning rate of 0 and no schedule (a cosine would rise to its floor): the weights stay where they start
    train(tmp_path, *common, "trainer.max_steps=3", "module.optimizer.lr=0.0", "module.scheduler=null",
          f"init_from={first}", f"hydra.run.dir={tmp_path / 'second'}")
    before = torch.load(first, weights_only=False)
    after = torch.load(tmp_path / "second" / "checkpoints" / "last.ckpt", weights_only=False)
    assert after["global_step"] == 3  # its own step count, not the first run's 6 + 3
    assert float(next(iter(after["optimizer_states"][0]["state"].values()))["step"]) == 3  # a fresh Adam
    assert before["state_dict"].keys() == after["state_dict"].keys()
    for name, value in before["state_dict"].items():
        assert torch.equal(after["state_dict"][name], value), name
    # a network of another width: refused, naming the file
    wider = train(tmp_path, *common, "trainer.max_steps=3", f"init_from={first}", "model.latent=24",
                  f"hydra.run.dir={tmp_path / 'third'}", check=False)
    assert wider.returncode != 0 and f"{first}: its weights do not fit" in wider.stderr
    both = train(tmp_path, *common, "trainer.max_steps=3", f"init_from={first}", f"resume={first}",
                 f"hydra.run.dir={tmp_path / 'fourth'}", check=False)
    assert both.returncode != 0 and "init_from and resume both set" in both.stderr
    # a deeper R-GNS with init_grow: the checkpoint's blocks, then one added (train.py passes the option on)
    train(tmp_path, *common, "trainer.max_steps=3", "module.optimizer.lr=0.0", "module.scheduler=null",
          f"init_from={first}", "init_grow=true", "model.layers=3", f"hydra.run.dir={tmp_path / 'fifth'}")
    grown = torch.load(tmp_path / "fifth" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    assert set(grown) - set(before["state_dict"]) == {n for n in grown if n.startswith("model.processor.blocks.2.")}
    for name, value in before["state_dict"].items():
        assert torch.equal(grown[name], value), name
    alone = train(tmp_path, *common, "trainer.max_steps=3", "init_grow=true", f"hydra.run.dir={tmp_path / 'sixth'}",
                  check=False)
    assert alone.returncode != 0 and "init_grow=true grows the model of init_from" in alone.stderr
    # `~init_from` after an init_from= (a script's command with the start file taken out): a run from scratch
    # (learning rate 0: its weights stay the fresh initialisation, not the first run's)
    train(tmp_path, *common, "trainer.max_steps=3", "module.optimizer.lr=0.0", "module.scheduler=null",
          f"init_from={first}", "~init_from", f"hydra.run.dir={tmp_path / 'seventh'}")
    fresh = torch.load(tmp_path / "seventh" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    assert any(not torch.equal(fresh[name], value) for name, value in before["state_dict"].items())


def rgns_module(**model) -> SimulatorModule:
    """A module around a small pairwise R-GNS (16 wide, 2 blocks unless ``model`` says otherwise)."""
    model = {"_target_": "rgns.models.RGNS", "latent": 16, "layers": 2, "couplings": "pairwise", **model}
    return SimulatorModule(model, dict(make_metadata(), gravity=[0.0, -9.81]),
                           {"_target_": "rgns.training.losses.LossDesign", "name": "DL4"},
                           {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 1e-3})


def test_warm_start_fills_only_the_parameters_an_option_starts_at_zero(tmp_path):
    """A checkpoint without the density condition warm-starts a model with it (that map keeps its
    zeros, the rest is the checkpoint's); a checkpoint lacking any other weight is refused."""
    def module(density: bool) -> SimulatorModule:
        return rgns_module(density_condition=density)

    source = module(False)
    with torch.no_grad():
        for parameter in source.parameters():
            parameter.add_(0.1)
    torch.save({"state_dict": source.state_dict()}, tmp_path / "plain.ckpt")
    target = module(True)
    warm_start(target, str(tmp_path / "plain.ckpt"))
    loaded = target.state_dict()
    assert torch.equal(loaded["model.density_encoder.weight"], torch.zeros(16, 2))
    for name, value in source.state_dict().items():
        assert torch.equal(loaded[name], value), name
    state = source.state_dict()
    del state["model.edge_encoder.0.weight"]
    torch.save({"state_dict": state}, tmp_path / "short.ckpt")
    with pytest.raises(CheckpointError, match="short.ckpt: its weights do not fit"):
        warm_start(module(True), str(tmp_path / "short.ckpt"))


def test_average_of_checkpoints_is_the_mean_of_their_weights_and_loads(tmp_path):
    """python -m rgns.training.average OUT A B: OUT's weights are A's and B's mean, it loads as a
    simulator; a checkpoint of another model is refused naming the file, and OUT is not written."""
    from rgns.training.average import average_checkpoints, main
    from rgns.training.module import load_simulator

    paths = []
    for seed in (0, 1, 2):
        torch.manual_seed(seed)
        module = rgns_module()
        with torch.no_grad():
            for parameter in module.parameters():
                parameter.normal_()
        paths.append(tmp_path / f"run{seed}.ckpt")
        torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                    "optimizer_states": [{"state": {}}], "global_step": 10 + seed}, paths[-1])
    out = tmp_path / "soup" / "mean.ckpt"
    assert main([str(out), *map(str, paths)]) == 0
    weights = [torch.load(path, weights_only=True)["state_dict"] for path in paths]
    soup = torch.load(out, weights_only=True)
    assert "optimizer_states" not in soup and soup["averaged_from"] == list(map(str, paths))
    floats = [name for name, value in weights[0].items() if value.is_floating_point()]
    assert len(floats) > 10
    for name in floats:
        torch.testing.assert_close(soup["state_dict"][name], sum(w[name] for w in weights) / 3, rtol=1e-6, atol=1e-7)
    moved = [name for name in floats if not torch.equal(weights[0][name], weights[1][name])]  # the parameters
    assert len(moved) > 10 and all(not torch.equal(soup["state_dict"][name], weights[0][name]) for name in moved)
    simulator, _ = load_simulator(str(out))
    torch.testing.assert_close(simulator.state_dict()["projection.weight"], soup["state_dict"]["model.projection.weight"])
    # another width: refused, naming it; nothing written
    wider = rgns_module(latent=24)
    torch.save({"state_dict": wider.state_dict(), "hyper_parameters": dict(wider.hparams)}, tmp_path / "wide.ckpt")
    refused = tmp_path / "refused.ckpt"
    assert main([str(refused), str(paths[0]), str(tmp_path / "wide.ckpt")]) == 1
    assert not refused.exists()
    with pytest.raises(CheckpointError, match="wide.ckpt: another model"):
        average_checkpoints([str(paths[0]), str(tmp_path / "wide.ckpt")])
    with pytest.raises(ValueError, match="at least two"):
        average_checkpoints([str(paths[0])])


def test_init_grow_adds_identity_blocks_that_predict_what_the_shallower_model_did(tmp_path):
    """A 2-block R-GNS checkpoint warm-starts a 4-block one with init_grow: blocks 0-1 are the
    checkpoint's, blocks 2-3 keep their identity initialisation, and the deeper model's forward
    and inverse steps are the shallower one's. Moved off the identity, the added blocks change
    the step. Without init_grow the deeper model is refused, as is growth that adds nothing
    or a model whose blocks do not start as the identity."""
    def module(layers: int, zero_init: bool = True) -> SimulatorModule:
        return rgns_module(layers=layers, galilean=True, zero_init=zero_init, edges="updated").double()

    source = module(2)
    perturb(source)
    path = tmp_path / "shallow.ckpt"
    torch.save({"state_dict": source.state_dict()}, path)
    grown = module(4)
    initial = {name: value.clone() for name, value in grown.state_dict().items()}
    warm_start(grown, str(path), grow=True)
    added = {name for name in initial if name.startswith(("model.processor.blocks.2.", "model.processor.blocks.3.",
                                                          "model.processor.edge_updates.2.",
                                                          "model.processor.edge_updates.3."))}
    assert added and set(grown.state_dict()) == set(source.state_dict()) | added
    for name, value in grown.state_dict().items():
        assert torch.equal(value, initial[name] if name in added else source.state_dict()[name]), name

    state = random_state(kinematic=0)
    state = State(state.position.double(), state.velocity_history.double(), state.particle_type, state.batch)
    for direction in ("step", "inverse_step"):
        before, after = getattr(source.model, direction)(state), getattr(grown.model, direction)(state)
        assert before.velocity_history.abs().max() > 0
        assert torch.allclose(after.velocity_history, before.velocity_history, rtol=0, atol=1e-12), direction
        assert torch.allclose(after.position, before.position, rtol=0, atol=1e-12), direction
    perturb(grown.model.processor.blocks[2], seed=1)
    moved = grown.model.step(state).velocity_history
    assert (moved - source.model.step(state).velocity_history).abs().max() > 1e-6

    with pytest.raises(CheckpointError, match="shallow.ckpt: its weights do not fit"):
        warm_start(module(4), str(path))
    with pytest.raises(CheckpointError, match="shallow.ckpt: init_grow=true, but"):
        warm_start(module(2), str(path), grow=True)
    with pytest.raises(CheckpointError, match="shallow.ckpt: init_grow=true, but"):
        warm_start(module(4, zero_init=False), str(path), grow=True)


def test_non_finite_loss_stops_and_keeps_the_last_checkpoint(dataset, tmp_path):
    run = tmp_path / "run"
    common = ["data=folder", f"data.root={dataset}", "trainer=cpu", "trainer.val_check_interval=5",
              f"hydra.run.dir={run}", *TINY]
    train(tmp_path, *common, "trainer.max_steps=10")
    last = run / "checkpoints" / "last.ckpt"
    before = last.read_bytes()
    # the same run continued with a loss weight that makes the loss NaN at its first step
    failed = train(tmp_path, *common, "trainer.max_steps=20", f"resume={last}", "module.inverse_weight=nan", check=False)
    assert failed.returncode != 0
    assert "non-finite training loss" in failed.stderr
    assert last.read_bytes() == before
    assert torch.load(last, weights_only=False)["global_step"] == 10


def test_gradient_norm_is_logged_before_clipping_with_each_batchs_pushed_steps(dataset, tmp_path):
    """train/grad_norm is the gradient's norm as the loss made it: with a clip far below it
    (trainer.gradient_clip_val), every logged norm is still above the clip. train/pushed is the
    number of pushed steps each batch drew from the schedule."""
    run = tmp_path / "run"
    train(tmp_path, "data=folder", f"data.root={dataset}", "trainer=cpu", "trainer.max_steps=8",
          "trainer.val_check_interval=8", "recipe=pushforward", "module.pushforward.steps=[-1,-1]",
          "module.pushforward.unrolls=[0,2]", "module.pushforward.probs=[1,1]", "data.lead=2",
          "+trainer.gradient_clip_val=1e-6", f"hydra.run.dir={run}", *TINY)
    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    norms = [e.value for e in events.Scalars("train/grad_norm")]
    pushed = [e.value for e in events.Scalars("train/pushed")]
    assert len(norms) == len(pushed) == 8
    assert min(norms) > 1e-3  # a million times the clip: logged before clipping
    assert set(pushed) == {0.0, 2.0}  # both entries of the schedule drawn (train.py seeds the draws)


def test_validation_rollouts_score_the_averaged_weights(dataset, tmp_path):
    """With an EMA callback the checkpoint holds the averaged weights, and the validation rollout
    that chooses checkpoints must score those same weights, not the raw ones."""
    from rgns.data.contract import Split
    from rgns.training.module import load_simulator
    from rgns.training.rollouts import forward_rollout

    run = tmp_path / "run"
    train(tmp_path, "data=folder", f"data.root={dataset}", "trainer=cpu", "trainer.max_steps=12",
          "trainer.val_check_interval=12", "module.optimizer.lr=1e-2", "callbacks.early_stopping=null", EMA,
          f"hydra.run.dir={run}", *TINY)
    checkpoint = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    assert checkpoint["global_step"] == 12 and "current_model_state" in checkpoint  # averaged and raw kept
    raw, averaged = checkpoint["current_model_state"], checkpoint["state_dict"]
    assert max((raw[k] - averaged[k]).abs().max() for k in averaged if k in raw) > 1e-4  # the two differ

    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    (logged,) = [e.value for e in events.Scalars("val/rollout_mse") if e.step >= 11]
    model, info = load_simulator(str(run / "checkpoints" / "last.ckpt"))
    k, steps = info["hparams"]["history"], info["hparams"]["val_rollout_steps"]
    with Split(dataset / "valid.h5") as valid:
        position, particle_type = (torch.from_numpy(a) for a in valid[0])
    n = min(steps, len(position) - k - 1)
    with torch.no_grad():
        mse = (forward_rollout(model, position, particle_type, k, n) - position[k + 1 : k + 1 + n]).pow(2).mean()
    assert logged == pytest.approx(mse.item(), rel=1e-4)


def test_compiled_training_saves_an_eager_checkpoint(dataset, tmp_path):
    """module.compile=true: training steps run compiled (the EMA's copy and validation eager),
    and the checkpoint holds a model that loads and runs eager."""
    from rgns.training.module import load_simulator

    run = tmp_path / "run"
    train(tmp_path, "data=folder", f"data.root={dataset}", "trainer=cpu", "trainer.max_steps=6",
          "trainer.val_check_interval=3", "module.compile=true", "model.memory_saving=false", EMA,
          f"hydra.run.dir={run}", *TINY)
    model, info = load_simulator(str(run / "checkpoints" / "last.ckpt"))
    assert info["global_step"] == 6 and info["hparams"]["compile"] is True
    assert not model.compiled
    assert "val/rollout_mse" in scalar_tags(run)


def test_progress_line_time_left_counts_this_fits_steps_after_a_resume(capsys):
    """A resumed run begins at its checkpoint's step: the time left comes from the steps this fit
    made, not from the global step (which made it ~40x too short at step 1,189 of 5,000)."""
    import time
    from types import SimpleNamespace

    from rgns.training.progress import TimeSplit

    split = TimeSplit(every_s=1.0, force_lines=True)
    trainer = SimpleNamespace(global_step=1000, max_steps=5000, global_rank=0)
    split.on_fit_start(trainer, None)
    for batch_idx in range(100):             # 100 steps from the resumed step 1,000
        split.on_train_batch_start(trainer, None, None, batch_idx)
        trainer.global_step += 1
        split.on_train_batch_end(trainer, None, {"loss": 1.0}, None, batch_idx)
    now = time.perf_counter()
    split._fit_start = now - 100.0           # 100 s into this fit
    split._print_line(trainer, {"loss": 1.0}, now)
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("[train] step 1100/5000: loss 1")
    assert line.endswith("~65.0 min left")    # 3,900 steps at 1 s each
