"""Neural SPH: the quintic kernel, the SPH relaxation (a compressed lattice relaxes, a resting one
stays at rest), the external force taken out of training and added back, relaxation at inference
only, and training through the LightningModule."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from omegaconf import OmegaConf
from torch_geometric.data import Batch

from conftest import make_metadata, perturb, train_steps
from conftest import random_state as shared_random_state
from rgns import config_dir
from rgns.data.contract import KINEMATIC, WATER, open_split
from rgns.data.graph import radius_graph
from rgns.data.windows import WindowDataset
from rgns.models import GNS, NeuralSPH, State, count_parameters
from rgns.models.neural_sph import (DEFAULT_SPACING, SPHRelaxation, dataset_spacing, quintic_kernel,
                                    quintic_kernel_derivative)
from rgns.training.module import SimulatorModule

torch.set_num_threads(1)
K = 5
SMALL = dict(latent=16, layers=2)
GRAVITY = [0.0, -9.81]
SPACING = 0.09  # of random_state's particles


def metadata(dim: int = 2, radius: float = 0.1, **extra) -> dict:
    return dict(bounds=[[0.1, 0.9]] * dim, default_connectivity_radius=radius, dim=dim, dt=0.0025,
                sequence_length=100, vel_mean=[1e-4] * dim, vel_std=[1e-3] * dim, acc_mean=[1e-6] * dim,
                acc_std=[1e-4] * dim, **extra)


def lattice(side: int, dim: int) -> torch.Tensor:
    """A square (cubic) lattice of ``side^D`` points at spacing 1, float64.  ``[side^D, D]``"""
    axis = torch.arange(side, dtype=torch.float64)
    return torch.stack(torch.meshgrid(*[axis] * dim, indexing="ij"), dim=-1).reshape(-1, dim)


def walled_lattice(fluid: int, wall: int, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A ``fluid^D`` block of water inside ``wall`` layers of kinematic particles, one lattice."""
    position = lattice(fluid + 2 * wall, dim)
    inside = ((position >= wall) & (position < wall + fluid)).all(dim=-1)
    return position, torch.where(inside, WATER, KINEMATIC)


def random_state(particles: int = 60, dim: int = 2, kinematic: int = 6, seed: int = 0) -> State:
    return shared_random_state(particles, dim, kinematic, seed, history=K)


# ---- the kernel -------------------------------------------------------------------------------

@pytest.mark.parametrize("dim", [1, 2, 3])
def test_quintic_kernel_integrates_to_one_and_its_derivative_is_exact(dim):
    fine = 0.1  # a Riemann sum over a fine lattice
    points = (lattice(61, dim) - 30) * fine
    assert (quintic_kernel(points.norm(dim=-1), dim) * fine**dim).sum().item() == pytest.approx(1.0, rel=1e-6)
    q = torch.linspace(0.01, 3.2, 200, dtype=torch.float64, requires_grad=True)
    (autograd,) = torch.autograd.grad(quintic_kernel(q, dim).sum(), q)
    assert torch.allclose(quintic_kernel_derivative(q, dim), autograd, rtol=1e-10, atol=1e-14)
    assert quintic_kernel(torch.tensor(3.0), dim) == 0 and quintic_kernel_derivative(torch.tensor(0.0), dim) == 0


# ---- the relaxation -----------------------------------------------------------------------------

@pytest.mark.parametrize("dim", [2, 3])
def test_resting_lattice_stays_at_rest(dim):
    """Water on the lattice of spacing dx, walled in by kinematic particles of the same lattice: every
    density is the lattice's (1 + 6e-5, inside the bounds), the pressure uniform, no particle moves."""
    spacing = 0.0065
    position, particle_type = walled_lattice(fluid=6 if dim == 2 else 4, wall=6, dim=dim)
    relaxation = SPHRelaxation(dim, spacing, loops=3)
    water = particle_type == WATER
    density = relaxation.density(position, radius_graph(position, 3.0))
    assert density[water].sub(1).abs().max() < 1e-3
    relaxed = relaxation(position * spacing, particle_type)
    assert (relaxed - position * spacing).abs().max() / spacing < 1e-12
    # a free block: the particles the surface does not reach (farther than 3 dx, plus the 3 dx of
    # their neighbours' densities) stay at rest; those near it feel the free-surface treatment
    block = lattice(16, dim) if dim == 2 else lattice(10, dim)
    moved = (SPHRelaxation(dim, 1.0)(block, torch.full((len(block),), WATER)) - block).norm(dim=-1)
    deep = ((block >= 4) & (block <= block.max() - 4)).all(dim=-1)
    assert moved[deep].max() < 1e-12 and moved[~deep].max() > 1e-4


def compressed_lattice(dim: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """The walled lattice with its water pulled towards the centre of the block (densities up to ~1.012)."""
    position, particle_type = walled_lattice(fluid=12, wall=6, dim=dim)
    centre = position[particle_type == WATER].mean(0)
    offset = position - centre
    pull = 0.008 * offset * torch.exp(-offset.pow(2).sum(-1, keepdim=True) / 9.0)
    return torch.where((particle_type == WATER).unsqueeze(-1), position - pull, position), particle_type


def test_relaxation_lowers_the_density_error_of_a_compressed_lattice():
    position, particle_type = compressed_lattice()
    water = particle_type == WATER
    relaxation = SPHRelaxation(2, 1.0)  # the paper's settings: 1 loop, alpha 0.015, c0 10

    def error(x: torch.Tensor) -> float:
        return relaxation.density(x, radius_graph(x, 3.0))[water].sub(1).abs().mean().item()

    density = relaxation.density(position, radius_graph(position, 3.0))
    assert 1.01 < density.max() < relaxation.density_bounds[1]  # compressed, below the cap
    errors = [error(position)]
    for _ in range(5):
        position = relaxation(position, particle_type)
        errors.append(error(position))
    assert all(after < before for before, after in zip(errors, errors[1:]))
    assert errors[1] < 0.6 * errors[0] and errors[-1] < 0.2 * errors[0]  # one loop of the paper's settings halves it


def test_relaxation_pushes_a_displaced_particle_back():
    """One water particle moved 0.3 dx off its site in a resting lattice: the density rises ahead
    of it and falls behind it, and the pressure gradient pushes it back along the same axis."""
    position, particle_type = walled_lattice(fluid=6, wall=6, dim=2)
    i = int(((position - torch.tensor([8.0, 8.0])).norm(dim=-1) == 0).nonzero())  # water, in the middle
    position[i, 0] += 0.3
    relaxation = SPHRelaxation(2, 1.0)
    acceleration = relaxation.acceleration(position, radius_graph(position, 3.0))
    assert acceleration[i, 0] < -0.1 and acceleration[i, 1].abs() < 1e-12
    # pair forces are antisymmetric and the masses equal: the accelerations of all particles
    # (the kinematic ones' computed, not applied) sum to zero
    assert acceleration.sum(0).abs().max() < 1e-12
    relaxed = SPHRelaxation(2, 1.0, loops=5)(position, particle_type)
    assert 0 < relaxed[i, 0] - 8.0 < 0.25  # on its way back (0.3 -> 0.23 in 5 loops of alpha 0.015)


def test_free_surface_and_cap_of_the_density():
    relaxation = SPHRelaxation(2, 1.0)
    density, pressure = relaxation.pressure(torch.tensor([0.5, 0.979, 0.99, 1.0, 1.01, 1.5], dtype=torch.float64))
    expected = torch.tensor([1.0, 1.0, 0.99, 1.0, 1.01, 1.02], dtype=torch.float64)
    assert torch.equal(density, expected) and torch.allclose(pressure, 100 * (expected - 1))
    # an isolated close pair misses most neighbours (density ~ 0.4): a free surface, no pull, no push
    pair = torch.tensor([[0.0, 0.0], [0.5, 0.0]], dtype=torch.float64)
    assert relaxation.acceleration(pair, radius_graph(pair, 3.0)).abs().max() == 0


def test_relaxation_settings_are_checked():
    with pytest.raises(ValueError, match="spacing"):
        SPHRelaxation(2, 0.0)
    with pytest.raises(ValueError, match="density_bounds"):
        SPHRelaxation(2, 1.0, density_bounds=(1.01, 1.02))


# ---- the external force -----------------------------------------------------------------------

def test_gravity_and_spacing_come_from_the_dataset():
    g = torch.tensor(GRAVITY) * 0.0025**2
    meta = metadata(gravity=GRAVITY, generator={"params": {"spacing": 0.01}})
    model = NeuralSPH(meta, **SMALL)
    plain = GNS(meta, **SMALL)
    assert torch.allclose(model.gravity, g)
    assert torch.equal(model.acc_mean, plain.acc_mean - g)  # the target a - g: its mean shifts
    assert torch.equal(model.acc_std_noisy, plain.acc_std_noisy)  # its std does not
    assert model.relaxation.spacing == 0.01
    assert dataset_spacing(metadata()) == DEFAULT_SPACING and dataset_spacing(meta, 0.02) == 0.02
    # the scene object where Hydra's instantiate has built the generator's config (SimulatorModule)
    assert dataset_spacing(metadata(generator={"params": SimpleNamespace(spacing=0.01)})) == 0.01
    assert torch.allclose(NeuralSPH(meta, gravity=[0.0, -1.0], **SMALL).gravity, torch.tensor([0.0, -0.0025**2]))
    # data without gravity (DeepMind's): its mean acceleration stands in, as for the ballistic baseline
    assert torch.equal(NeuralSPH(metadata(), **SMALL).gravity, torch.tensor([1e-6, 1e-6]))
    with pytest.raises(ValueError, match="components"):
        NeuralSPH(metadata(dim=3, gravity=GRAVITY), **SMALL)


class GravityGNS(GNS):
    """GNS whose predicted velocity gets gravity added: the reference for zero relaxation loops."""

    def __init__(self, metadata: dict, gravity: torch.Tensor, **kwargs):
        super().__init__(metadata, **kwargs)
        self.register_buffer("gravity", gravity)

    def next_velocity(self, *args) -> torch.Tensor:
        return super().next_velocity(*args) + self.gravity


@pytest.mark.parametrize("hard_walls", [False, True])
def test_zero_loops_is_gns_plus_the_added_force(hard_walls):
    meta = metadata(gravity=GRAVITY)
    torch.manual_seed(0)
    model = NeuralSPH(meta, relaxation_loops=0, hard_walls=hard_walls, **SMALL).eval()
    perturb(model)
    g = torch.tensor(GRAVITY) * 0.0025**2
    shifted = dict(meta, acc_mean=(torch.tensor(meta["acc_mean"]) - g).tolist())  # statistics of a - g
    reference = GravityGNS(shifted, g, hard_walls=hard_walls, **SMALL).eval()
    reference.load_state_dict(model.state_dict())  # the same weights (and buffers)
    state = random_state()
    kinematic = state.position + 1e-3 * torch.arange(1, 9).view(-1, 1, 1)  # [8, N, D], moving walls
    assert torch.equal(model.rollout(state, 8, kinematic), reference.rollout(state, 8, kinematic))
    # with a uniform gravity and the shifted mean, it is GNS's prediction itself, up to rounding
    plain = GNS(meta, **SMALL).eval()
    weights = {key: value for key, value in model.state_dict().items() if key not in ("acc_mean", "gravity")}
    plain.load_state_dict(weights, strict=False)  # its own statistics, those of a
    edge_index = model.graph(state.position)
    args = (state.position, state.velocity_history, state.particle_type, edge_index)
    assert torch.allclose(model.next_velocity(*args), plain.next_velocity(*args), rtol=0, atol=1e-9)


# ---- relaxation in rollouts ---------------------------------------------------------------------

def relaxing_model(hard_walls: bool = False) -> NeuralSPH:
    # 60 particles in the 0.7 x 0.7 box: one per 0.09^2, the spacing that makes densities ~ 1
    torch.manual_seed(0)
    model = NeuralSPH(metadata(gravity=GRAVITY), spacing=SPACING, relaxation_loops=2, relaxation_step=0.05,
                      hard_walls=hard_walls, **SMALL)
    perturb(model, 0.01)
    return model


def test_relaxation_runs_in_eval_rollouts_only():
    model, state = relaxing_model(), random_state(seed=1)
    bare = NeuralSPH(metadata(gravity=GRAVITY), spacing=SPACING, relaxation_loops=0, **SMALL)
    bare.load_state_dict(model.state_dict())
    learned = bare.step(state)
    assert torch.equal(model.train().step(state).position, learned.position)  # training: no relaxation
    relaxed = model.eval().step(state)
    expected = model.relaxation(learned.position, state.particle_type)
    water = state.particle_type == WATER
    assert torch.allclose(relaxed.position, expected, atol=1e-7)
    assert (relaxed.position - learned.position)[water].abs().max() > 1e-5  # it moved the water
    # the shift is part of the newest velocity: p^{t+1} = p^t + v^{t+1}, the older ones move along
    assert torch.equal(relaxed.position, state.position + relaxed.velocity_history[:, -1])
    assert torch.equal(relaxed.velocity_history[:, :-1], state.velocity_history[:, 1:])


@pytest.mark.parametrize("hard_walls", [False, True])
def test_kinematic_particles_stay_where_the_base_class_puts_them(hard_walls):
    model, state = relaxing_model(hard_walls).eval(), random_state(seed=2)
    kinematic = state.particle_type == KINEMATIC
    told = state.position + 0.01  # imposed positions of frame t+1 (only kinematic rows read)
    bare = NeuralSPH(metadata(gravity=GRAVITY), spacing=SPACING, relaxation_loops=0, hard_walls=hard_walls, **SMALL)
    bare.load_state_dict(model.state_dict())
    relaxed, learned = model.step(state, told), bare.eval().step(state, told)
    assert torch.equal(relaxed.position[kinematic], learned.position[kinematic])
    assert torch.equal(relaxed.velocity_history[kinematic], learned.velocity_history[kinematic])


def test_hard_walls_keep_relaxed_particles_in_the_box():
    model = relaxing_model(hard_walls=True).eval()
    state = random_state(seed=3)
    state.position[:10, 0] = 0.1  # on the wall, pressed together
    state.position[:10, 1] = 0.5 + 0.004 * torch.arange(10)
    positions = model.rollout(state, 5)
    low, high = model.bounds[:, 0], model.bounds[:, 1]
    assert ((positions >= low) & (positions <= high)).all()


# ---- size and training ------------------------------------------------------------------------

def test_default_size_is_gns_sized():
    cfg = OmegaConf.to_container(OmegaConf.load(config_dir() / "model" / "neural_sph.yaml"))
    cfg.pop("_target_")
    meta = metadata(gravity=GRAVITY)
    model = NeuralSPH(meta, **cfg)
    assert count_parameters(model) == count_parameters(GNS(meta)) == 1_591_826  # paper: 1.72 M (GNS 1.59 M)
    assert model.relaxation.loops == 1 and model.relaxation.step == 0.015 and model.relaxation.sound_speed == 10.0
    assert NeuralSPH.display_name == "NeuralSPH" and not NeuralSPH.bidirectional


def test_training_steps_through_the_module(tiny_dataset):
    model = {"_target_": "rgns.models.NeuralSPH", "latent": 16, "layers": 2}
    # the generator's scene config, as generated metadata carries it (the module's instantiate builds it)
    generator = {"params": {"_target_": "types.SimpleNamespace", "spacing": 0.01}}
    module = SimulatorModule(model, dict(make_metadata(), gravity=GRAVITY, generator=generator),
                             {"_target_": "rgns.training.losses.LossDesign", "name": "DL4"},
                             {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 1e-3}, noise_std=1e-4)
    assert module.model.relaxation.spacing == 0.01
    windows = WindowDataset(open_split(tiny_dataset, "train"), radius=0.08, history=K, noise_std=1e-4)
    batch = Batch.from_data_list([windows[0], windows[len(windows) - 1]])
    losses = train_steps(module, batch, steps=15, lr=1e-3)
    assert all(math.isfinite(v) for v in losses) and losses[-1] < losses[0]
