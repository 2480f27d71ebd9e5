"""Training recipes (pushforward, unrolled losses) and hard walls: what each promises, checked on
tiny data."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from torch_geometric.data import Batch

from conftest import make_metadata
from rgns.data.contract import WATER, open_split
from rgns.data.graph import kernel_density, radius_graph
from rgns.data.windows import WindowDataset
from rgns.models import GNS, State
from rgns.models.base import Simulator
from rgns.training.losses import density_error
from rgns.training.module import SimulatorModule
from rgns.training.recipes import Pushforward, Unroll

MODEL = {"_target_": "rgns.models.GNS", "latent": 8, "layers": 1}
LOSS = {"_target_": "rgns.training.losses.LossDesign", "name": "DL4"}
OPTIMIZER = {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 1e-3}


def test_pushforward_draws_only_entries_whose_step_has_passed():
    schedule = Pushforward(steps=[-1, 10, 20], unrolls=[0, 1, 2], probs=[0, 1, 1])
    generator = torch.Generator().manual_seed(0)
    assert {schedule.draw(5, generator) for _ in range(50)} == {0}  # only the first entry, weight 0
    assert {schedule.draw(15, generator) for _ in range(50)} == {1}
    assert {schedule.draw(25, generator) for _ in range(200)} == {1, 2}
    assert schedule.max_unrolls == 2
    with pytest.raises(ValueError, match="same length"):
        Pushforward(steps=[-1], unrolls=[0, 1], probs=[1, 1])


def test_unroll_length_grows_on_its_schedule():
    schedule = Unroll(steps=[0, 100, 300], lengths=[1, 3, 5])
    assert [schedule.length(s) for s in (0, 99, 100, 299, 300, 10_000)] == [1, 1, 3, 3, 5, 5]
    with pytest.raises(ValueError):
        Unroll(steps=[0, 10], lengths=[2, 0])


def windows_batch(root, lead: int, horizon: int) -> Batch:
    split = open_split(root, "train")
    windows = WindowDataset(split, radius=0.08, history=5, noise_std=1e-4, lead=lead, horizon=horizon)
    return Batch.from_data_list([windows[0], windows[len(windows) - 1]])


def module_with(pushforward=None, unroll=None, lead: int = 0, step: int = 100) -> SimulatorModule:
    module = SimulatorModule(MODEL, make_metadata(), LOSS, OPTIMIZER, noise_std=1e-4,
                             pushforward=pushforward, unroll=unroll)
    # what the module reads of its trainer in a training step
    module._trainer = SimpleNamespace(datamodule=SimpleNamespace(lead=lead), global_step=step)
    return module


def record_starts(module: SimulatorModule) -> list[torch.Tensor]:
    """Wrap the model's step: record, per call, the position of the state it starts from."""
    starts, step = [], module.model.step

    def recorded(state, kinematic_position=None):
        starts.append(state.position.detach().clone())
        return step(state, kinematic_position)

    module.model.step = recorded
    return starts


def record_steps(module: SimulatorModule) -> list[bool]:
    """Wrap the model's step: record, per call, whether gradients were being recorded."""
    calls, step = [], module.model.step

    def recorded(state, kinematic_position=None):
        calls.append(torch.is_grad_enabled())
        return step(state, kinematic_position)

    module.model.step = recorded
    return calls


def test_window_frames_cover_lead_and_horizon(tiny_dataset):
    batch = windows_batch(tiny_dataset, lead=3, horizon=4)
    assert batch.frames.shape[1] == 3 + 5 + 1 + 4
    split = open_split(tiny_dataset, "train")
    windows = WindowDataset(split, radius=0.08, history=5, lead=3, horizon=4)
    s, t = windows.index[0]
    assert t == 5 + 3  # the first frame with the lead and the history before it
    first = windows[0]
    position, _ = split[s]
    torch.testing.assert_close(first.frames[:, 3 + 5], torch.from_numpy(position[t]))  # p^t at index lead + k


def test_pushforward_unrolls_its_steps_without_gradients(tiny_dataset):
    module = module_with(pushforward={"steps": [-1], "unrolls": [3], "probs": [1]}, lead=3)
    calls = record_steps(module)
    terms = module._losses(windows_batch(tiny_dataset, lead=3, horizon=1))
    assert calls == [False, False, False, True]  # three pushed steps, then the one trained on
    terms["loss"].backward()
    assert all(p.grad is not None for p in module.model.parameters() if p.requires_grad)


def test_early_windows_fill_in_the_lead_with_the_first_frame(tiny_dataset):
    split = open_split(tiny_dataset, "train")
    plain = WindowDataset(split, radius=0.08, history=5, lead=0, horizon=2)
    early = WindowDataset(split, radius=0.08, history=5, lead=3, horizon=2, early_windows=True)
    assert early.index == plain.index  # no target is dropped for the lead
    position, _ = split[early.index[0][0]]
    position = torch.from_numpy(position)
    first, second = early[0], early[1]  # t = 5 and 6: 0 and 1 real frames before the history
    assert early.index[0][1] == 5 and first.frames.shape[1] == 3 + 5 + 1 + 2
    assert first.lead_frames.tolist() == [0] * len(position[0]) and int(second.lead_frames[0]) == 1
    for j in range(3):  # the missing lead frames are the first frame
        torch.testing.assert_close(first.frames[:, j], position[0])
    torch.testing.assert_close(first.frames[:, 3:], position[: 5 + 1 + 2].transpose(0, 1))
    torch.testing.assert_close(second.frames[:, 2:], position[: 6 + 1 + 2].transpose(0, 1))
    late = early[len(early) - 1]
    assert int(late.lead_frames[0]) == 3  # far enough in: the whole lead is real


def pushed_three_steps(windows: list) -> tuple[Batch, list[torch.Tensor]]:
    """Batch the windows, push them 3 steps (no noise, data.lead=3) and train on the next:
    the batch and the start position of every model step taken."""
    batch = Batch.from_data_list(windows)
    module = SimulatorModule(MODEL, make_metadata(), LOSS, OPTIMIZER, noise_std=0.0,
                             pushforward={"steps": [-1], "unrolls": [3], "probs": [1]})
    module._trainer = SimpleNamespace(datamodule=SimpleNamespace(lead=3), global_step=100)
    starts = record_starts(module)
    module._losses(batch)
    return batch, starts


def test_pushforward_from_an_early_window_starts_at_its_own_first_frame(tiny_dataset):
    split = open_split(tiny_dataset, "train")
    windows = WindowDataset(split, radius=0.08, history=5, lead=3, horizon=1, early_windows=True)
    early, late = windows[1], windows[len(windows) - 1]  # 1 and 3 real frames before the history
    batch, starts = pushed_three_steps([early, late])
    assert len(starts) == 4  # three pushed steps and the trained one
    first, second = batch.batch == 0, batch.batch == 1
    # the early window waits two steps at the first state its frames hold (history from the
    # trajectory's frame 0, at index 2; position at index 2 + 5), then is pushed once; the late
    # one is pushed from the state 3 frames before p^t
    for j in range(3):
        torch.testing.assert_close(starts[j][first], early.frames[:, 2 + 5])
    assert not torch.equal(starts[3][first], early.frames[:, 2 + 5])
    torch.testing.assert_close(starts[0][second], late.frames[:, 5])
    assert not torch.equal(starts[1][second], late.frames[:, 5])


def test_pushforward_skips_the_steps_every_early_window_is_held_through(tiny_dataset):
    split = open_split(tiny_dataset, "train")
    windows = WindowDataset(split, radius=0.08, history=5, lead=3, horizon=1, early_windows=True)
    none, one = windows[0], windows[1]  # 0 and 1 real frames before the history: held 3 and 2 steps
    batch, starts = pushed_three_steps([none, one])
    assert len(starts) == 2  # the two steps both windows wait through are not computed
    first, second = batch.batch == 0, batch.batch == 1
    # the pushed step starts from both windows' first states; the trained step finds the first
    # window still held there and the second pushed once from it
    torch.testing.assert_close(starts[0][first], none.frames[:, 3 + 5])
    torch.testing.assert_close(starts[0][second], one.frames[:, 2 + 5])
    torch.testing.assert_close(starts[1][first], none.frames[:, 3 + 5])
    assert not torch.equal(starts[1][second], one.frames[:, 2 + 5])


def test_pushforward_asks_for_the_frames_it_needs(tiny_dataset):
    module = module_with(pushforward={"steps": [-1], "unrolls": [3], "probs": [1]}, lead=1)
    with pytest.raises(ValueError, match="data.lead >= 3"):
        module._losses(windows_batch(tiny_dataset, lead=1, horizon=1))


def test_unrolled_loss_has_gradients_through_every_step(tiny_dataset):
    module = module_with(unroll={"steps": [0], "lengths": [3]})
    batch = windows_batch(tiny_dataset, lead=0, horizon=3)
    states, recording = [], []
    step = module.model.step

    def keep(state, kinematic_position=None):
        recording.append(torch.is_grad_enabled())
        state = step(state, kinematic_position)
        state.position.retain_grad()
        state.velocity_history.retain_grad()
        states.append(state)
        return state

    module.model.step = keep
    terms = module._losses(batch)
    assert recording == [True, True, True]
    terms["loss"].backward()
    # every step's predicted velocity feeds the loss, and so does every position but the last,
    # through the steps after it
    assert all(s.velocity_history.grad is not None and s.velocity_history.grad[:, -1].abs().sum() > 0 for s in states)
    assert all(s.position.grad is not None and s.position.grad.abs().sum() > 0 for s in states[:-1])


def test_one_step_unroll_with_clean_input_is_the_position_error(tiny_dataset):
    """With no noise, one unrolled step's MSE is the error of the predicted next position,
    in units of the acceleration std."""
    module = module_with(unroll={"steps": [0], "lengths": [2]})
    module.hparams.noise_std = 0.0
    batch = windows_batch(tiny_dataset, lead=0, horizon=2)
    terms = module._losses(batch)
    k = 5
    frames = batch.frames
    state = State(frames[:, k], (frames[:, 1 : k + 1] - frames[:, :k]), batch.particle_type, batch.batch)
    with torch.no_grad():
        errors = []
        for j in range(2):
            state = module.model.step(state, kinematic_position=frames[:, k + j + 1])
            moving = batch.particle_type == WATER
            errors.append((((state.position - frames[:, k + j + 1]) / module.model.acc_std_noisy)[moving] ** 2).mean())
    torch.testing.assert_close(terms["forward_mse"].detach(), torch.stack(errors).mean(), rtol=1e-4, atol=0)


@pytest.mark.parametrize("target", ["velocity", "acceleration"])
def test_multistep_target_asks_the_reached_state_for_the_true_velocity_or_acceleration(tiny_dataset, target):
    """multistep_target: from the state the model reached (not the true one), the second unrolled
    step is asked for the true next velocity, or the true acceleration at that frame, instead of
    the true next position; the first step starts from the clean truth, so all three agree on it."""
    module = module_with(unroll={"steps": [0], "lengths": [2]})
    module.hparams.noise_std, module.hparams.multistep_target = 0.0, target
    batch = windows_batch(tiny_dataset, lead=0, horizon=2)
    terms = module._losses(batch)
    k, frames, scale = 5, batch.frames, module.model.acc_std_noisy
    moving = batch.particle_type == WATER
    state = State(frames[:, k], (frames[:, 1 : k + 1] - frames[:, :k]), batch.particle_type, batch.batch)
    errors, drifted = [], []
    with torch.no_grad():
        for j in range(2):
            velocity = state.velocity_history[:, -1]
            state = module.model.step(state, kinematic_position=frames[:, k + j + 1])
            predicted = state.velocity_history[:, -1]
            true_velocity = frames[:, k + j + 1] - frames[:, k + j]
            if target == "velocity":
                error = predicted - true_velocity
            else:
                error = (predicted - velocity) - (true_velocity - (frames[:, k + j] - frames[:, k + j - 1]))
            errors.append(((error / scale)[moving] ** 2).mean())
            drifted.append(((state.position - frames[:, k + j + 1]) / scale)[moving].pow(2).mean())
    torch.testing.assert_close(terms["forward_mse"].detach(), torch.stack(errors).mean(), rtol=1e-4, atol=0)
    # the second step's state has drifted, so the position error there differs from these targets
    assert not torch.allclose(torch.stack(errors), torch.stack(drifted), rtol=1e-3)
    torch.testing.assert_close(errors[0], drifted[0], rtol=1e-4, atol=0)


def test_multistep_target_refuses_an_unknown_name():
    with pytest.raises(ValueError, match="multistep_target must be one of"):
        SimulatorModule(MODEL, make_metadata(), LOSS, OPTIMIZER, multistep_target="positions")


@pytest.mark.parametrize("scale", [0.0, 1.0])
def test_unrolled_loss_starts_from_positions_with_the_position_noise_asked_for(tiny_dataset, scale):
    """position_noise scales the start frame's share of the random-walk noise in the multi-step
    loss as in the one-step windows: 0 starts from the clean frame, 1 from GNS's noisy one."""
    module = module_with(unroll={"steps": [0], "lengths": [2]})
    module.hparams.noise_std, module.hparams.position_noise = 1e-2, scale
    batch = windows_batch(tiny_dataset, lead=0, horizon=2)
    starts = record_starts(module)
    module._losses(batch)
    moving = batch.particle_type == WATER
    offset = (starts[0] - batch.frames[:, 5])[moving].abs().max()
    assert (offset == 0) if scale == 0 else (offset > 1e-3)


def test_unrolled_loss_draws_a_noise_level_per_window(tiny_dataset, monkeypatch):
    """noise_low in the multi-step loss: each graph of the batch gets its own level (here drawn as
    0 and 1: the first window starts clean, the second with the full noise)."""
    import rgns.training.module as module_code

    module = module_with(unroll={"steps": [0], "lengths": [2]})
    module.hparams.noise_std, module.hparams.noise_low = 1e-2, 0.0
    drawn = []
    monkeypatch.setattr(module_code, "noise_level",
                        lambda low, size=None: drawn.append((low, size)) or torch.tensor([0.0, 1.0]))
    batch = windows_batch(tiny_dataset, lead=0, horizon=2)
    starts = record_starts(module)
    module._losses(batch)
    assert drawn == [(0.0, 2)]
    offset = (starts[0] - batch.frames[:, 5]).abs().max(dim=1).values  # [N]
    moving = batch.particle_type == WATER
    first, second = moving & (batch.batch == 0), moving & (batch.batch == 1)
    assert offset[first].max() == 0 and offset[second].max() > 1e-3


def test_kernel_density_counts_each_neighbour_by_its_distance():
    torch.manual_seed(0)
    position, radius = torch.rand(60, 2) * 0.3, 0.08
    rho = kernel_density(position, radius_graph(position, radius), radius)
    distance = torch.cdist(position, position)
    brute = ((1 - (distance / radius) ** 2).clamp(min=0) ** 3).sum(1)  # the diagonal is the 1 for itself
    torch.testing.assert_close(rho, brute)
    pair = torch.tensor([[0.0, 0.0], [radius, 0.0]])  # a neighbour at the radius adds nothing
    torch.testing.assert_close(kernel_density(pair, torch.tensor([[0, 1], [1, 0]]), radius), torch.ones(2))


def test_density_error_is_zero_on_the_truth_and_grows_with_compression():
    xs, ys = torch.meshgrid(torch.arange(8) * 0.02, torch.arange(8) * 0.02, indexing="ij")
    truth = torch.stack([xs.flatten(), ys.flatten()], -1) + 0.2
    mask = torch.ones(len(truth), dtype=torch.bool)
    errors = []
    for squeeze in (1.0, 0.95, 0.85):
        predicted = truth.mean(0) + squeeze * (truth - truth.mean(0))
        pairs = torch.cat([radius_graph(predicted, 0.05), radius_graph(truth, 0.05)], 1).unique(dim=1)
        errors.append(float(density_error(predicted, truth, pairs, 0.05, mask)))
    assert errors[0] == 0 and 0 < errors[1] < errors[2]


def test_density_term_adds_the_clean_frames_density_error_to_the_unrolled_loss(tiny_dataset):
    """density_weight: each unrolled step adds the predicted positions' density error against
    the clean true frame, weighted, and the loss has gradients through it."""
    module = module_with(unroll={"steps": [0], "lengths": [2]})
    plain = module_with(unroll={"steps": [0], "lengths": [2]})
    plain.load_state_dict(module.state_dict())
    module.hparams.density_weight = 3.0
    for m in (module, plain):
        m.hparams.noise_std = 0.0  # no noise: both runs see the same inputs
    batch = windows_batch(tiny_dataset, lead=0, horizon=2)
    terms, reference = module._losses(batch), plain._losses(batch)
    assert "forward_density" not in reference
    # by hand: the model's two steps from the clean window, each against its clean true frame
    k, frames = 5, batch.frames
    moving = batch.particle_type == WATER
    state = State(frames[:, k], (frames[:, 1 : k + 1] - frames[:, :k]), batch.particle_type, batch.batch)
    errors = []
    with torch.no_grad():
        for j in range(2):
            state = module.model.step(state, kinematic_position=frames[:, k + j + 1])
            truth = frames[:, k + j + 1]
            pairs = torch.cat([module.model.graph(state.position, batch.batch),
                               module.model.graph(truth, batch.batch)], 1).unique(dim=1)
            errors.append(density_error(state.position, truth, pairs, module.model.radius, moving))
    density = torch.stack(errors).mean()
    assert density > 0
    torch.testing.assert_close(terms["forward_density"].detach(), density, rtol=1e-4, atol=0)
    torch.testing.assert_close(terms["forward_loss"].detach(), reference["forward_loss"].detach() + 3.0 * density,
                               rtol=1e-4, atol=1e-7)
    module.model.zero_grad()
    terms["forward_density"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in module.model.parameters())


def test_density_term_compares_with_the_clean_frame_under_noise(tiny_dataset, monkeypatch):
    """With noise, the position targets move with the start frame's noise; the density term's
    target is the clean true frame all the same."""
    import rgns.training.module as module_code

    module = module_with(unroll={"steps": [0], "lengths": [2]})
    module.hparams.noise_std, module.hparams.density_weight = 1e-2, 1.0
    seen = []
    monkeypatch.setattr(module_code, "density_error",
                        lambda predicted, target, *rest: seen.append(target) or predicted.sum() * 0)
    batch = windows_batch(tiny_dataset, lead=0, horizon=2)
    module._losses(batch)
    assert len(seen) == 2
    for j, target in enumerate(seen):
        torch.testing.assert_close(target, batch.frames[:, 5 + j + 1], rtol=0, atol=0)


def test_density_weight_needs_a_multistep_recipe():
    with pytest.raises(ValueError, match="recipe=unroll"):
        SimulatorModule(MODEL, make_metadata(), LOSS, OPTIMIZER, density_weight=1.0)
    with pytest.raises(ValueError, match="negative"):
        SimulatorModule(MODEL, make_metadata(), LOSS, OPTIMIZER, density_weight=-1.0, unroll={"steps": [0], "lengths": [2]})


def test_wall_gradient_through_keeps_the_clamped_step_and_passes_the_unclamped_gradient():
    """A particle 0.5 mm above the floor moving 2 mm down stops at the floor either way; with
    "stop" its step has no gradient along the clamped axis, with "through" the unclamped step's."""
    position = torch.tensor([[0.5, 0.1005], [0.5, 0.5]])
    velocity = torch.tensor([[0.001, -0.002], [0.0, 0.001]])
    module = SimulatorModule(MODEL, make_metadata(), LOSS, OPTIMIZER, wall_gradient="through")
    assert module.model.wall_gradient == "through"
    steps, grads = {}, {}
    for mode in ("stop", "through"):
        module.model.wall_gradient = mode
        v = velocity.clone().requires_grad_()
        steps[mode] = module.model.stop_at_walls(position, v)
        (steps[mode] * torch.tensor([[2.0, 3.0], [5.0, 7.0]])).sum().backward()
        grads[mode] = v.grad
    torch.testing.assert_close(steps["stop"], torch.tensor([[0.001, -0.0005], [0.0, 0.001]]))
    assert torch.equal(steps["through"], steps["stop"])
    assert torch.equal(grads["stop"], torch.tensor([[2.0, 0.0], [5.0, 7.0]]))
    assert torch.equal(grads["through"], torch.tensor([[2.0, 3.0], [5.0, 7.0]]))
    with pytest.raises(ValueError, match="wall_gradient"):
        SimulatorModule(MODEL, make_metadata(), LOSS, OPTIMIZER, wall_gradient="sideways")


class Falling(Simulator):
    """A stand-in network that pushes particles into the floor: forward it predicts a fall,
    backward an earlier frame below the floor."""

    bidirectional = True

    def next_velocity(self, position, velocity_history, particle_type, edge_index, batch=None):
        return velocity_history[:, -1] + torch.tensor([0.0, -1e-3])

    def oldest_velocity(self, position, velocity_history, particle_type, edge_index, batch=None):
        return velocity_history[:, 0] + torch.tensor([0.0, 1e-3])  # p^{t-k} = p^{t-k+1} - v: below


def resting_lattice() -> State:
    xs, ys = torch.meshgrid(torch.linspace(0.2, 0.3, 6), torch.tensor([0.1]), indexing="ij")
    position = torch.stack([xs.flatten(), ys.flatten()], -1)  # one row on the floor
    return State(position, torch.zeros(len(position), 5, 2), torch.full((len(position),), WATER))


@pytest.mark.parametrize("direction", ["step", "inverse_step"])
def test_hard_walls_keep_a_resting_lattice_at_rest(direction):
    state = resting_lattice()
    start = state.position.clone()
    model = Falling(make_metadata(), hard_walls=True)
    for _ in range(10):
        state = getattr(model, direction)(state)
    torch.testing.assert_close(state.position, start, rtol=0, atol=0)
    assert state.velocity_history.abs().max() == 0  # the wall took the velocity into it
    loose = Falling(make_metadata(), hard_walls=False)
    for _ in range(6):  # without the wall: forward it falls through, backward it came from below
        state = getattr(loose, direction)(state if _ else resting_lattice())
    assert state.velocity_history.abs().max() > 0
    if direction == "step":
        assert state.position[:, 1].max() < 0.1


def test_hard_walls_keep_every_rollout_in_the_box():
    torch.manual_seed(0)
    model = GNS(make_metadata(), latent=8, layers=1, hard_walls=True)
    with torch.no_grad():  # a network that throws particles about
        for p in model.decoder.parameters():
            p.mul_(1e4)
    state = State(torch.rand(30, 2) * 0.8 + 0.1, torch.randn(30, 5, 2) * 1e-2, torch.full((30,), WATER))
    positions = model.rollout(state, 20)
    assert positions.min() < 0.101 and positions.max() > 0.899  # it does throw them at the walls
    assert positions.min() >= 0.1 - 1e-6 and positions.max() <= 0.9 + 1e-6  # float32 round-off of p + v only
    # p^{t+1} = p^t + v^{t+1} still holds
    final = model.step(State(positions[-1], state.velocity_history, state.particle_type))
    torch.testing.assert_close(final.position - positions[-1], final.velocity_history[:, -1])


@pytest.mark.parametrize("batch, world, expected", [(2, 1, 1e-3), (8, 1, 4e-3), (4, 2, 4e-3)])
def test_learning_rate_scales_with_the_batch(batch, world, expected):
    module = SimulatorModule(MODEL, make_metadata(), LOSS, OPTIMIZER, lr_reference_batch=2,
                             scheduler={"_target_": "torch.optim.lr_scheduler.CosineAnnealingLR", "_partial_": True})
    module._trainer = SimpleNamespace(datamodule=SimpleNamespace(batch_size=batch), world_size=world,
                                      estimated_stepping_batches=100)
    configured = module.configure_optimizers()
    optimizer, scheduler = configured["optimizer"], configured["lr_scheduler"]["scheduler"]
    assert optimizer.param_groups[0]["lr"] == pytest.approx(expected)
    assert scheduler.base_lrs == [pytest.approx(expected)]  # the schedule starts from the scaled lr
    unscaled = SimulatorModule(MODEL, make_metadata(), LOSS, OPTIMIZER)
    unscaled._trainer = module._trainer
    assert unscaled.configure_optimizers().param_groups[0]["lr"] == pytest.approx(1e-3)
