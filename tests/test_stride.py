"""``data.stride``: training on every k-th frame, and scoring such a model on the ordinary data
at the same frames as every other method."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import make_metadata

from rgns import config_dir
from rgns.data.contract import KINEMATIC, WATER, metadata_differences, open_split, read_metadata
from rgns.data.datamodule import ParticleDataModule, at_stride
from rgns.data.windows import StridedSplit, WindowDataset
from rgns.errors import ConfigError
from rgns.evaluation.baselines import ConstantVelocity
from rgns.evaluation.methods import Method
from rgns.evaluation.tasks import Dataset, ForwardRollout
from rgns.training.rollouts import fill_frames, forward_rollout, strided_inverse_then_forward

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")


def datamodule(root, stride: int = 1, history: int = 2, **options) -> ParticleDataModule:
    return ParticleDataModule(str(root), history=history, noise_std=0.0, num_workers=0, stride=stride, **options)


# ---- data ------------------------------------------------------------------------------------

@pytest.mark.parametrize("stride", [2, 3])
def test_strided_windows_are_the_frames_they_were_cut_from_and_every_phase_is_used(tiny_dataset, stride):
    k = 2
    data = datamodule(tiny_dataset, stride, history=k)
    data.setup("fit")
    with open_split(tiny_dataset, "train") as train:
        raw = [torch.from_numpy(p) for p, _ in train]
    targets = [set() for _ in raw]  # the raw frame of each window's p^{t+1}
    for i, (s, t) in enumerate(data.train_set.index):
        phase, trajectory = divmod(s, len(raw))
        frames = raw[trajectory][phase + stride * (t - k) : phase + stride * (t + 1) + 1 : stride]  # [k+2, N, D]
        velocity = frames[1:] - frames[:-1]
        window = data.train_set[i]
        assert torch.equal(window.forward_input, velocity[:-1].transpose(0, 1))
        assert torch.equal(window.forward_target, velocity[-1])
        assert torch.equal(window.inverse_target, velocity[0])
        torch.testing.assert_close(window.pos, frames[-2], rtol=0, atol=1e-6)
        targets[trajectory].add(phase + stride * (t + 1))
    for trajectory, position in zip(targets, raw):  # every frame with k+1 strided frames before it is a target
        assert trajectory == set(range(stride * (k + 1), len(position)))
    # validation rollouts see strided trajectories too, phase 0 of each first
    first = data.valid_trajectories[0].position
    with open_split(tiny_dataset, "valid") as valid:
        assert torch.equal(first, torch.from_numpy(valid[0].position[::stride]))


def test_strided_statistics_are_those_of_frames_k_apart(tiny_dataset):
    stride = 3
    metadata = datamodule(tiny_dataset, stride).metadata
    with open_split(tiny_dataset, "train") as train:
        moving = [np.asarray(p, dtype=np.float64)[:, t != KINEMATIC] for p, t in train]
    velocity = np.concatenate([(p[stride:] - p[:-stride]).reshape(-1, 2) for p in moving])  # x[t+k] - x[t]
    acceleration = np.concatenate([(p[2 * stride:] - 2 * p[stride:-stride] + p[:-2 * stride]).reshape(-1, 2)
                                   for p in moving])
    np.testing.assert_allclose(metadata["vel_mean"], velocity.mean(0), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(metadata["vel_std"], velocity.std(0), rtol=1e-9)
    np.testing.assert_allclose(metadata["acc_mean"], acceleration.mean(0), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(metadata["acc_std"], acceleration.std(0), rtol=1e-9)
    stored = read_metadata(tiny_dataset)
    assert metadata["dt"] == pytest.approx(stride * stored["dt"], rel=1e-12) and metadata["stride"] == stride
    assert metadata["sequence_length"] == (stored["sequence_length"]) // stride
    assert metadata["vel_std"] != stored["vel_std"]  # the fixture's are made up: the strided ones are computed


def test_stride_one_is_the_data_as_it_is(tiny_dataset):
    default, one = ParticleDataModule(str(tiny_dataset), noise_std=0.0), datamodule(tiny_dataset, 1, history=5)
    assert one.metadata == default.metadata == dict(read_metadata(tiny_dataset), particle_types=[KINEMATIC, WATER])
    assert "stride" not in one.metadata and at_stride(one.metadata, 1) is not None
    one.setup("fit")
    assert type(one.split("train")).__name__ == "Split"  # not a StridedSplit
    plain = WindowDataset(open_split(tiny_dataset, "train"), one.radius, 5)
    assert one.train_set.index == plain.index
    for i in (0, len(plain) // 2, len(plain) - 1):
        assert torch.equal(one.train_set[i].forward_input, plain[i].forward_input)


@pytest.mark.parametrize("stride", [0, -1, 1.5, True, "2", None])
def test_a_stride_that_is_not_a_whole_number_of_frames_is_refused(tiny_dataset, stride):
    with pytest.raises(ConfigError, match=f"data.stride={stride!r}"):
        datamodule(tiny_dataset, stride)


def test_a_stride_that_leaves_a_trajectory_shorter_than_a_window_is_refused(tiny_dataset):
    # 20 frames: at stride 4 the shortest phase holds 5, a window of history 5 needs 7
    with pytest.raises(Exception, match=r"train\.h5, trajectory 00000: data\.stride=4 leaves 5 frames") as error:
        datamodule(tiny_dataset, 4, history=5).prepare_data()
    assert type(error.value).__name__ == "DatasetError"
    assert datamodule(tiny_dataset, 2, history=5).check()  # 10 frames a phase: enough


def test_strided_split_reads_each_phase():
    class Frames:  # a split of two trajectories of 7 and 9 frames, one particle whose x is the frame
        shapes = [(7, 1, 1), (9, 1, 1)]

        def __len__(self):
            return 2

        def __getitem__(self, i):
            return np.arange(self.shapes[i][0], dtype=np.float32)[:, None, None], np.array([WATER])

    strided = StridedSplit(Frames(), 3)
    assert strided.shapes == [(3, 1, 1), (3, 1, 1), (2, 1, 1), (3, 1, 1), (2, 1, 1), (3, 1, 1)]
    assert [p[:, 0, 0].tolist() for p, _ in strided] == [[0, 3, 6], [0, 3, 6], [1, 4], [1, 4, 7], [2, 5], [2, 5, 8]]


# ---- rollouts at a stride -------------------------------------------------------------------

def test_fill_frames_puts_the_frames_between_steps_on_straight_lines():
    first, strided = torch.zeros(1, 1), torch.tensor([[[3.0]], [[9.0]]])
    assert fill_frames(first, strided, 3)[:, 0, 0].tolist() == [1.0, 2.0, 3.0, 5.0, 7.0, 9.0]
    assert fill_frames(first, strided, 1) is strided


def uniform_motion(frames: int = 30, accelerating: bool = False):
    """20 water particles moving right at one speed (or speeding up), and 4 resting kinematic ones."""
    rng = np.random.default_rng(1)
    start = rng.uniform(0.3, 0.5, (24, 2))
    t = np.arange(frames, dtype=np.float64)[:, None, None]
    shift = (1e-4 * t**2 if accelerating else 2e-3 * t) * np.array([1.0, 0.0])
    position = np.broadcast_to(start, (frames, 24, 2)).copy()
    position[:, :20] += shift
    particle_type = torch.full((24,), WATER)
    particle_type[20:] = KINEMATIC
    return torch.tensor(position, dtype=torch.float32), particle_type


def test_constant_velocity_at_a_stride_scores_as_at_stride_one_on_uniform_motion():
    position, particle_type = uniform_motion()
    metadata = make_metadata(frames=30)
    model = ConstantVelocity(metadata, history=2)
    one = Method("every frame", model, None, "baseline")
    two = Method("every 2nd frame", model, None, "baseline", trained_metadata={"stride": 2})
    dataset = Dataset("uniform", "", metadata, [(position, particle_type)], start=4)
    results, examples = ForwardRollout(steps=None, distribution_steps=(1,))([one, two], dataset)
    assert results["settings"]["shared_stride"] == 2
    rows = results["methods"]
    assert rows["every 2nd frame"]["stride"] == 2 and rows["every frame"]["stride"] == 1
    assert len(rows["every 2nd frame"]["mse_per_step"]) == len(rows["every frame"]["mse_per_step"]) == 30 - 1 - 4
    for row in rows.values():  # exact up to float32 rounding, on the frames both predict and on all
        assert row["rollout_mse_shared"] < 1e-11 and row["rollout_mse"] < 1e-11
    assert rows["every 2nd frame"]["rollout_mse_shared"] == pytest.approx(rows["every frame"]["rollout_mse_shared"],
                                                                          abs=1e-11)
    truth = position[5:]
    torch.testing.assert_close(examples["predicted"]["every 2nd frame"], truth, rtol=0, atol=2e-6)


def test_the_frames_between_strided_steps_are_straight_lines_and_the_shared_mse_is_theirs():
    position, particle_type = uniform_motion(accelerating=True)  # truth is curved: the filled frames are not it
    model = ConstantVelocity(make_metadata(frames=30), history=2)
    start, steps = 6, 23  # odd: the last of its 12 steps of 3 frames reaches past the trajectory's end
    predicted = forward_rollout(model, position, particle_type, start, steps, stride=3)
    assert predicted.shape == (steps, 24, 2)
    frames = torch.cat([position[start][None], predicted])  # frames start .. start + steps
    for j in range(0, steps - 3, 3):  # between frames start+j and start+j+3
        torch.testing.assert_close(frames[j + 1], (2 * frames[j] + frames[j + 3]) / 3, rtol=0, atol=1e-6)
        torch.testing.assert_close(frames[j + 2], (frames[j] + 2 * frames[j + 3]) / 3, rtol=0, atol=1e-6)
    # its own steps: constant velocity over 3 frames, from the state of frames start-6, start-3, start
    velocity = position[start] - position[start - 3]
    torch.testing.assert_close(predicted[2], position[start] + velocity, rtol=0, atol=1e-6)
    assert not torch.allclose(predicted[0], position[start + 1], atol=1e-5)  # not the (curved) truth
    assert torch.equal(predicted[:, 20:], position[start + 1 :, 20:])  # kinematic: the truth at every frame
    # stride 1 here is the plain rollout
    assert torch.equal(forward_rollout(model, position, particle_type, start, 5),
                       forward_rollout(model, position, particle_type, start, 5, stride=1))

    one = Method("every frame", model, None, "baseline")
    three = Method("every 3rd frame", model, None, "baseline", trained_metadata={"stride": 3})
    dataset = Dataset("curved", "", make_metadata(frames=30), [(position, particle_type)], start=start)
    rows = ForwardRollout(steps=steps, distribution_steps=(1,))([one, three], dataset)[0]["methods"]
    for row in rows.values():
        curve = np.asarray(row["mse_per_step"])
        assert row["rollout_mse_shared"] == pytest.approx(curve[2::3].mean(), rel=1e-6)
        assert row["rollout_mse"] == pytest.approx(curve.mean(), rel=1e-6)
    assert rows["every frame"]["rollout_mse_shared"] != pytest.approx(rows["every 3rd frame"]["rollout_mse_shared"])


def test_a_start_too_early_for_a_strided_history_names_the_method_and_the_start():
    position, particle_type = uniform_motion()
    strided = Method("GNS every 3rd", ConstantVelocity(make_metadata(), history=2), None, "x.ckpt",
                     trained_metadata={"stride": 3})
    dataset = Dataset("uniform", "", make_metadata(), [(position, particle_type)], start=5)
    with pytest.raises(ConfigError, match=r"start=5: GNS every 3rd \(x.ckpt\) .* needs start >= 6"):
        ForwardRollout(steps=5)([strided], dataset)


def test_strided_inverse_then_forward_is_exact_for_constant_velocity():
    position, particle_type = uniform_motion()
    model = ConstantVelocity(make_metadata(frames=30), history=2)
    inferred, resimulated = strided_inverse_then_forward(model, position, particle_type, start=6, steps=8, stride=2)
    assert inferred.shape == resimulated.shape == (8, 24, 2)
    torch.testing.assert_close(inferred, position[6:14].flip(0), rtol=0, atol=2e-6)  # frames 13 .. 6
    torch.testing.assert_close(resimulated, position[7:15], rtol=0, atol=2e-6)  # frames 7 .. 14
    with pytest.raises(ValueError, match="not a whole number of steps of 2 frames"):
        strided_inverse_then_forward(model, position, particle_type, start=6, steps=5, stride=2)


def test_a_strided_checkpoint_is_compared_with_its_data_at_its_stride(tiny_dataset):
    stored = dict(read_metadata(tiny_dataset))
    trained = datamodule(tiny_dataset, 2).metadata
    assert metadata_differences(trained, at_stride(stored, 2)) == []
    differences = metadata_differences(trained, stored)  # as metadata.json gives it: stride, dt and the stats
    assert any("'stride' 2 (trained) against 1" in d for d in differences)
    assert any(d.startswith("'dt'") for d in differences)
    assert any("'dt'" in d for d in metadata_differences(trained, at_stride(dict(stored, dt=0.01), 2)))


# ---- train.py and evaluate.py ---------------------------------------------------------------

def test_a_stride_2_run_trains_and_is_scored_on_the_stride_1_data(dataset, tmp_path):
    run = tmp_path / "run"
    subprocess.run(
        [sys.executable, "train.py", "data=folder", f"data.root={dataset}", "data.stride=2", "model=rgns",
         "model.latent=16", "model.layers=2", "history=3", "trainer=cpu", "trainer.max_steps=4",
         "trainer.val_check_interval=2", "data.num_workers=0", "logger=tensorboard", f"hydra.run.dir={run}"],
        cwd=ROOT, env=ENV, check=True, capture_output=True, timeout=300)
    checkpoint = run / "checkpoints" / "last.ckpt"
    hparams = torch.load(checkpoint, map_location="cpu", weights_only=False)["hyper_parameters"]
    stored = read_metadata(dataset)
    assert hparams["metadata"]["stride"] == 2 and hparams["metadata"]["dt"] == pytest.approx(2 * stored["dt"])

    from hydra import compose, initialize_config_dir

    from rgns.evaluation.run import evaluate

    out = tmp_path / "evaluation"
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=[
            f"ckpt_path={checkpoint}", f"output_dir={out}", "trajectories=1", "task.forward.distribution_steps=[1]",
            "task.efficiency.repeats=1", "task.efficiency.memory=false", "task.inverse.horizons=[1,2,4]",
            "task.inverse.table_horizon=2", "animation.max_frames=4",
            "baselines={constant_velocity:{_target_:"
            "rgns.evaluation.baselines.ConstantVelocity}}"])
    results = evaluate(cfg)
    on_disk = json.loads((out / "results.json").read_text())
    data = on_disk["datasets"][dataset.name]
    assert on_disk["warnings"] == []  # its own data at its stride: nothing to warn about
    forward, inverse, cost = (data[k]["methods"] for k in ("forward", "inverse", "efficiency"))
    label = next(label for label in forward if label.startswith("R-GNS"))
    assert data["forward"]["settings"]["start"] == 2 * 3  # its history, 2 frames a velocity
    assert data["forward"]["settings"]["shared_stride"] == 2
    steps = 30 - 1 - 6
    assert len(forward[label]["mse_per_step"]) == len(forward["Const. velocity"]["mse_per_step"]) == steps
    assert forward[label]["stride"] == 2 and forward["Const. velocity"]["stride"] == 1
    for row in forward.values():  # one trajectory: the mean of its curve at frames t0 + 2, t0 + 4, ..
        assert row["rollout_mse_shared"] == pytest.approx(np.mean(row["mse_per_step"][1::2]), rel=1e-6)
    assert cost[label]["forward_ms_per_frame"] == pytest.approx(cost[label]["forward_ms_per_step"] / 2)
    baseline = cost["Const. velocity"]
    assert baseline["forward_ms_per_frame"] == baseline["forward_ms_per_step"] and baseline["stride"] == 1
    summary = data["summary"][label]
    assert summary["stride"] == 2 and summary["forward_ms_per_frame"] == cost[label]["forward_ms_per_frame"]
    assert summary["rollout_mse_shared"] == forward[label]["rollout_mse_shared"]
    # the inverse task runs the horizons its stride allows, and passes over the others
    horizons = inverse[label]["horizons"]
    assert horizons["1"]["trajectories"] == 0 and "not_run" in horizons["1"] and horizons["1"]["consistency_mse"] is None
    assert horizons["2"]["trajectories"] == horizons["4"]["trajectories"] == 1
    assert horizons["4"]["consistency_mse"] is not None and inverse[label]["stride"] == 2
    assert results["datasets"][dataset.name]["forward"]["methods"][label]["stride"] == 2
    report = (out / "report.md").read_text()  # the report's efficiency table: the stride and ms per frame too
    assert "| Stride (frames per step) | 2 | 1 |" in report
    assert f"| Forward Inference Time (ms/frame) | {cost[label]['forward_ms_per_frame']:.4g} |" in report

    # a start earlier than its 3 velocities of 2 frames is refused, naming it
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"ckpt_path={checkpoint}", f"output_dir={tmp_path / 'early'}",
                                             "start=5", "task=forward"])
    with pytest.raises(ConfigError, match=r"start=5: R-GNS 16x2 .* needs start >= 6"):
        evaluate(cfg)
    # the goal task steps a model one frame at a time: refused, naming it, before any work
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("evaluate", overrides=[f"ckpt_path={checkpoint}", f"output_dir={tmp_path / 'goal'}", "task=goal"])
    with pytest.raises(ConfigError, match=r"task.goal: R-GNS 16x2 .*\(data.stride=2\)"):
        evaluate(cfg)
    # and the analysis tools, which step one frame at a time, refuse it by name
    from rgns.evaluation import onestep
    with pytest.raises(ConfigError, match=r"last.ckpt: steps 2 frames at a time \(data.stride=2\)"):
        onestep.main([str(checkpoint)])
