import shutil

import pytest
import torch
from torch_geometric.data import Data
from torch_geometric.loader import DataLoader

from rgns.data.contract import KINEMATIC, open_split
from rgns.data.datamodule import ParticleDataModule, ResumableLoader
from rgns.data.graph import radius_graph
from rgns.data.windows import WindowDataset, noise_level, random_walk_noise

K = 5


@pytest.fixture
def split(tiny_dataset):
    with open_split(tiny_dataset, "train", min_frames=K + 2) as data:
        yield data


def test_windows_cover_every_frame(split):
    windows = WindowDataset(split, radius=0.08, history=K)
    assert len(windows) == 3 * (20 - K - 1)


def test_clean_window_holds_both_directions(split):
    windows = WindowDataset(split, radius=0.08, history=K)
    position = torch.from_numpy(split[0].position)
    velocity = position[1:] - position[:-1]
    sample = windows[3]  # trajectory 0, t = K + 3
    t = K + 3
    torch.testing.assert_close(sample.pos, position[t], rtol=0, atol=1e-6)
    torch.testing.assert_close(sample.forward_input, velocity[t - K : t].transpose(0, 1), rtol=0, atol=1e-6)
    torch.testing.assert_close(sample.forward_target, velocity[t], rtol=0, atol=1e-6)
    torch.testing.assert_close(sample.inverse_input, velocity[t - K + 1 : t + 1].transpose(0, 1), rtol=0, atol=1e-6)
    torch.testing.assert_close(sample.inverse_target, velocity[t - K], rtol=0, atol=1e-6)


def test_noisy_inputs_clean_velocity_targets(split):
    torch.manual_seed(0)
    windows = WindowDataset(split, radius=0.08, history=K, noise_std=1e-2)
    position = torch.from_numpy(split[1].position)
    velocity = position[1:] - position[:-1]
    t = K + 2
    sample = windows[(20 - K - 1) + 2]  # trajectory 1, t = K + 2
    moving = sample.particle_type != KINEMATIC
    assert not torch.allclose(sample.pos, position[t])  # positions and input velocities are noisy ...
    assert not torch.allclose(sample.forward_input[:, -1][moving], velocity[t - 1][moving])
    # ... the targets are the clean velocities (GNS): v^{t+1} forward, v^{t-k+1} inverse
    torch.testing.assert_close(sample.forward_target, velocity[t], rtol=0, atol=1e-6)
    torch.testing.assert_close(sample.inverse_target, velocity[t - K], rtol=0, atol=1e-6)
    # the noise is a random walk from the clean oldest frame: p~^t = p^{t-k} + sum of noisy velocities
    torch.testing.assert_close(sample.pos, position[t - K] + sample.forward_input.sum(1), rtol=0, atol=1e-6)
    # the two histories are one window shifted by a frame
    torch.testing.assert_close(sample.inverse_input[:, :-1], sample.forward_input[:, 1:])
    kinematic = sample.particle_type == KINEMATIC
    assert kinematic.any()
    torch.testing.assert_close(sample.pos[kinematic], position[t][kinematic], rtol=0, atol=0)


def gns_and_variant(split, **variant):
    """Trajectory 1's clean positions, t = K + 2, and its window at t with GNS's noise and with a
    noise ``variant`` of the same draw."""
    i = (20 - K - 1) + 2  # trajectory 1, t = K + 2
    torch.manual_seed(0)
    plain = WindowDataset(split, radius=0.08, history=K, noise_std=1e-2)[i]
    torch.manual_seed(0)
    sample = WindowDataset(split, radius=0.08, history=K, noise_std=1e-2, **variant)[i]
    return torch.from_numpy(split[1].position), K + 2, plain, sample


@pytest.mark.parametrize("fraction", [0.25, 1.0])
def test_position_correction_takes_back_that_fraction_of_the_position_noise(split, fraction):
    """The forward target lands p~^t + target on the clean p^{t+1} plus (1 - fraction) of p~^t's noise;
    the inputs and the inverse target are those of plain GNS noise (same draw)."""
    position, t, plain, sample = gns_and_variant(split, position_correction=fraction)
    torch.testing.assert_close(sample.forward_input, plain.forward_input, rtol=0, atol=0)
    torch.testing.assert_close(sample.inverse_target, plain.inverse_target, rtol=0, atol=0)
    noise = sample.pos - position[t]
    assert noise.abs().max() > 1e-3  # the moving particles' positions are noisy
    landed = sample.pos + sample.forward_target
    torch.testing.assert_close(landed, position[t + 1] + (1 - fraction) * noise, rtol=0, atol=1e-6)


@pytest.mark.parametrize("scale", [0.0, 0.5])
def test_position_noise_scales_only_the_positions_share_of_the_noise(split, scale):
    """The input velocities and the targets are plain GNS noise's (same draw); p~^t is the clean
    p^t plus ``scale`` times GNS's position noise (0: clean positions)."""
    position, t, plain, sample = gns_and_variant(split, position_noise=scale)
    for key in ("forward_input", "forward_target", "inverse_input", "inverse_target"):
        torch.testing.assert_close(sample[key], plain[key], rtol=0, atol=0)
    assert (plain.pos - position[t]).abs().max() > 1e-3  # GNS's positions are noisy
    torch.testing.assert_close(sample.pos, position[t] + scale * (plain.pos - position[t]), rtol=0, atol=1e-6)


def window_noise_rms(split, noise_low: float) -> torch.Tensor:
    """The rms of each window's input-velocity noise (noisy - clean), over its moving particles."""
    torch.manual_seed(0)
    windows = WindowDataset(split, radius=0.08, history=K, noise_std=1e-2, noise_low=noise_low)
    clean = WindowDataset(split, radius=0.08, history=K)
    rms = []
    for i in range(len(windows)):  # 42 windows
        moving = windows[i].particle_type != KINEMATIC
        noise = windows[i].forward_input - clean[i].forward_input
        rms.append(noise[moving].pow(2).mean().sqrt())
    return torch.stack(rms)


def test_noise_low_draws_each_windows_noise_level_between_it_and_the_full_noise(split):
    fixed = window_noise_rms(split, 1.0)  # GNS: every window at noise_std
    full = fixed.median()
    assert fixed.min() > 0.7 * full and fixed.max() < 1.3 * full
    spread = window_noise_rms(split, 0.0)  # levels from clean to full
    assert spread.min() < 0.2 * full and spread.max() > 0.7 * full and spread.max() < 1.3 * full
    half = window_noise_rms(split, 0.5)
    assert half.min() > 0.5 * 0.7 * full and half.max() < 1.3 * full
    with pytest.raises(ValueError, match="noise_low"):
        WindowDataset(split, radius=0.08, history=K, noise_std=1e-2, noise_low=1.5)


def test_random_walk_noise_takes_a_level_per_particle():
    torch.manual_seed(0)
    level = torch.tensor([0.0, 1.0, 0.5])
    noise = random_walk_noise((6, 3, 2), 1.0, torch.tensor([True, True, True]), level)
    torch.manual_seed(0)
    plain = random_walk_noise((6, 3, 2), 1.0, torch.tensor([True, True, True]))
    torch.testing.assert_close(noise, plain * level[None, :, None], rtol=0, atol=0)
    assert noise_level(1.0) == 1.0
    levels = noise_level(0.25, size=1000)
    assert levels.min() >= 0.25 and levels.max() <= 1 and levels.std() > 0.15


def test_trajectory_cache_keeps_what_fits_and_changes_nothing(split):
    size = split[0].position.nbytes + split[0].particle_type.nbytes
    kept = WindowDataset(split, radius=0.08, history=K, cache_mb=1.5 * size / 2**20)  # room for one of three
    plain = WindowDataset(split, radius=0.08, history=K, cache_mb=0)
    order = [len(plain) - 1, 0, 5, len(plain) // 2, len(plain) - 2, 1]  # jumping between trajectories
    for i in order:
        a, b = kept[i], plain[i]
        for key in ("pos", "edge_index", "forward_input", "forward_target", "inverse_input", "inverse_target"):
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)
    assert list(kept._kept) == [kept.index[order[0]][0]]  # the first read, and no more: the budget holds
    assert plain._kept == {}
    # a trajectory read again comes from memory, not from the file
    s = kept.index[order[0]][0]
    position, _ = kept._trajectory(s)
    assert position is kept._kept[s][0]


def test_radius_graph_is_every_pair_within_radius():
    position = torch.rand(300, 3)
    edges = radius_graph(position, 0.2)
    distance = torch.cdist(position.double(), position.double())
    expected = ((distance < 0.2) & ~torch.eye(300, dtype=torch.bool)).nonzero().t()
    got = set(map(tuple, edges.t().tolist()))
    assert got == set(map(tuple, expected.t().tolist()))
    assert len(got) == edges.shape[1]  # no duplicates


def test_datamodule_batches_two_graphs(tiny_dataset):
    dm = ParticleDataModule(str(tiny_dataset), batch_size=2)
    dm.prepare_data()
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch.num_graphs == 2
    assert batch.forward_input.shape == (120, K, 2)
    assert int(batch.edge_index.max()) < 120
    # edges never join the two graphs
    assert (batch.batch[batch.edge_index[0]] == batch.batch[batch.edge_index[1]]).all()


def numbered(n: int) -> list[Data]:
    return [Data(number=torch.tensor([i])) for i in range(n)]


def order_of(batches) -> list[int]:
    return [int(i) for batch in batches for i in batch.number]


def test_training_order_is_the_shuffled_one_and_resumes_within_its_epoch():
    windows = numbered(23)
    torch.manual_seed(3)
    shuffled = order_of(DataLoader(windows, batch_size=2, shuffle=True))
    torch.manual_seed(3)
    loader = ResumableLoader(windows, batch_size=2)
    assert order_of(loader) == shuffled  # a run that is not resumed trains on the same windows as before
    assert sorted(shuffled) == list(range(23)) and shuffled != sorted(shuffled)

    torch.manual_seed(3)
    first = ResumableLoader(windows, batch_size=2)
    batches = iter(first)
    before = order_of(next(batches) for _ in range(4))
    state = first.state_dict()
    assert state["position"] == 8
    torch.manual_seed(99)  # the resumed process's own generator
    resumed = ResumableLoader(windows, batch_size=2)
    resumed.load_state_dict(state)
    assert before + order_of(resumed) == shuffled  # the rest of the epoch, no window twice
    assert resumed.state_dict() == {"seed": state["seed"], "position": 12 * 2}  # 12 batches, the last of one window
    assert sorted(order_of(resumed)) == list(range(23))  # then whole new epochs
    resumed.load_state_dict(resumed.state_dict())  # saved at an epoch's end: the next starts whole
    assert sorted(order_of(resumed)) == list(range(23))


def test_validation_windows_come_in_a_fixed_order_spread_over_the_split(tiny_dataset):
    """limit_val_batches validates on the first batches: they must not be one trajectory's first frames."""
    datamodule = ParticleDataModule(str(tiny_dataset), num_workers=0, noise_std=1e-2)
    datamodule.setup("fit")
    first = [(round(float(b.pos[0, 0]), 6), b.num_graphs) for b in list(datamodule.val_dataloader())[:4]]
    again = [(round(float(b.pos[0, 0]), 6), b.num_graphs) for b in list(datamodule.val_dataloader())[:4]]
    assert first == again  # the same windows at every validation
    loader = datamodule.val_dataloader()
    seen = [datamodule.valid_set.index[i] for i in loader.dataset.indices[: 4 * datamodule.batch_size]]
    assert {s for s, _ in seen} == {0, 1}  # both validation trajectories within the first 4 batches
    assert max(t for _, t in seen) - min(t for _, t in seen) > 5  # and frames far apart
    assert sorted(loader.dataset.indices) == list(range(len(datamodule.valid_set)))  # every window, once


def test_missing_dataset_names_the_command(tmp_path):
    dm = ParticleDataModule(str(tmp_path / "nowhere"))
    with pytest.raises(ValueError, match="rgns.data.generate"):
        dm.prepare_data()


def test_prepare_data_makes_a_missing_dataset(tmp_path, tiny_dataset):
    made = []

    def make(out_dir):
        made.append(out_dir)
        shutil.copytree(tiny_dataset, out_dir)

    dm = ParticleDataModule(str(tmp_path / "made"), make=make)
    dm.prepare_data()
    dm.prepare_data()
    assert made == [str(tmp_path / "made")]
    assert dm.metadata["dim"] == 2
