"""EGNN: equivariance to rotations, reflections and translations of the whole scene (gravity and
walls rotated with it), the named vectors it reads from the metadata, its stabilisers, and
training through the LightningModule."""
from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torch_geometric.data import Batch

from conftest import make_metadata, train_steps
from rgns.data.contract import KINEMATIC, WATER, open_split
from rgns.data.graph import radius_graph
from rgns.data.windows import WindowDataset
from rgns.models import EGNN, count_parameters
from rgns.nn.egnn import EquivariantLayer
from rgns.training.module import SimulatorModule

torch.set_num_threads(1)
K = 5
RADIUS = 0.1
CONFIG = Path(__file__).resolve().parents[1] / "conf" / "model" / "egnn.yaml"


def metadata(dim: int) -> dict:
    gravity = [0.0, -9.81] + [0.0] * (dim - 2)
    # axis-wise statistics that differ by axis: an axis-wise normalisation would break the symmetry
    return dict(make_metadata(dim, radius=RADIUS), gravity=gravity, vel_mean=[2e-4, -5e-4, 1e-4][:dim],
                vel_std=[1e-3, 2e-3, 1.5e-3][:dim], acc_mean=[1e-6, -4e-5, 0.0][:dim], acc_std=[5e-5, 8e-5, 6e-5][:dim])


def scene(dim: int, particles: int = 60, seed: int = 0, dtype=torch.float64):
    """A state near a corner of the box (walls within R), two particles coincident, a few kinematic."""
    generator = torch.Generator().manual_seed(seed)
    position = 0.1 + 0.3 * torch.rand(particles, dim, generator=generator, dtype=dtype)
    position[1] = position[0]
    velocity = 3e-3 * torch.randn(particles, K, dim, generator=generator, dtype=dtype)
    particle_type = torch.full((particles,), WATER)
    particle_type[-4:] = KINEMATIC
    velocity[-4:] = 0.0
    return position, velocity, particle_type


def random_model(dim: int, seed: int = 0, **options) -> EGNN:
    """A small float64 EGNN whose gates all matter: gain 1 and weights moved off their init."""
    torch.manual_seed(seed)
    model = EGNN(metadata(dim), history=K, latent=16, layers=3, **{"coordinate_gain": 1.0, **options}).double()
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.add_(0.05 * torch.randn(parameter.shape, generator=generator, dtype=parameter.dtype))
    return model


def orthogonal(dim: int, reflect: bool, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(dim, dim, generator=generator, dtype=torch.float64))
    if (torch.linalg.det(q) < 0) != reflect:
        q = q @ torch.diag(torch.tensor([-1.0] + [1.0] * (dim - 1), dtype=torch.float64))
    return q


# ---- what defines the model: E(n) equivariance once the named vectors move with the scene -------

@pytest.mark.parametrize("options", [{}, {"coordinate_aggregation": "sum", "normalise": True, "tanh": True}])
@pytest.mark.parametrize("reflect", [False, True])
@pytest.mark.parametrize("dim", [2, 3])
def test_rotating_and_translating_the_scene_rotates_and_translates_the_prediction(dim, reflect, options):
    model = random_model(dim, **options)
    position, velocity, particle_type = scene(dim)
    edge_index = radius_graph(position, RADIUS)
    gravity, walls = model.vector_inputs(position)
    assert edge_index.shape[1] > 4 * len(position) and (walls.norm(dim=-1) < RADIUS).any()  # neighbours and walls in range
    q = orthogonal(dim, reflect)
    shift = torch.tensor([0.7, -1.3, 2.1][:dim], dtype=torch.float64)

    next_velocity = model.predict(position, velocity, particle_type, edge_index, gravity, walls)
    moved = model.predict(position @ q.T + shift, velocity @ q.T, particle_type, edge_index, gravity @ q.T, walls @ q.T)

    # the network does something: accelerations of the order of the scale or more
    acceleration = (next_velocity - velocity[:, -1]) / model.acceleration_scale
    assert acceleration.abs().mean() > 0.3
    # p^{t+1} = p^t + v^{t+1} rotates and translates with the scene, to float64 precision
    expected = (position + next_velocity) @ q.T + shift
    scale = next_velocity.abs().max().item()
    torch.testing.assert_close(position @ q.T + shift + moved, expected, rtol=0, atol=1e-12 * scale + 1e-14)
    torch.testing.assert_close(moved, next_velocity @ q.T, rtol=0, atol=1e-12 * scale)
    # gravity and walls carry the only broken symmetry: left unrotated, the prediction is not rotated
    unrotated_gravity = model.predict(position @ q.T + shift, velocity @ q.T, particle_type, edge_index, gravity, walls @ q.T)
    unrotated_walls = model.predict(position @ q.T + shift, velocity @ q.T, particle_type, edge_index, gravity @ q.T, walls)
    for wrong in (unrotated_gravity, unrotated_walls):
        assert (wrong - next_velocity @ q.T).abs().max() > 1e-3 * scale


def test_next_velocity_reads_gravity_and_the_box_walls_from_the_metadata():
    model = random_model(2)
    position, velocity, particle_type = scene(2)
    position[2] = torch.tensor([0.105, 0.5], dtype=torch.float64)  # near the left wall, far from the others
    edge_index = radius_graph(position, RADIUS)
    gravity, walls = model.vector_inputs(position)
    torch.testing.assert_close(gravity, torch.tensor([0.0, -9.81 * 0.0025**2], dtype=torch.float64))
    # lower x, lower y, upper x, upper y: the vector to the wall's plane, clipped to R
    expected = torch.tensor([[-0.005, 0.0], [0.0, -0.1], [0.1, 0.0], [0.0, 0.1]], dtype=torch.float64)
    torch.testing.assert_close(walls[2], expected)
    torch.testing.assert_close(model.next_velocity(position, velocity, particle_type, edge_index),
                               model.predict(position, velocity, particle_type, edge_index, gravity, walls))


def test_a_batch_is_its_graphs_side_by_side():
    model = random_model(2)
    scenes = [scene(2, particles=30 + 10 * s, seed=s) for s in range(2)]
    alone = [model.next_velocity(p, v, t, radius_graph(p, RADIUS)) for p, v, t in scenes]
    position, velocity, particle_type = (torch.cat(parts) for parts in zip(*scenes))
    batch = torch.arange(2).repeat_interleave(torch.tensor([30, 40]))
    together = model.next_velocity(position, velocity, particle_type, model.graph(position, batch), batch)
    torch.testing.assert_close(together, torch.cat(alone))


def test_kinematic_particles_keep_their_velocity_through_the_layers():
    model = random_model(3)
    position, velocity, particle_type = scene(3)
    velocity[-4:] = 1e-3  # moving boundary particles
    predicted = model.next_velocity(position, velocity, particle_type, radius_graph(position, RADIUS))
    kinematic = particle_type == KINEMATIC
    torch.testing.assert_close(predicted[kinematic], velocity[kinematic, -1])
    assert not torch.allclose(predicted[~kinematic], velocity[~kinematic, -1])


# ---- the stabilisers and their defaults -----------------------------------------------------------

def test_zero_gain_starts_at_constant_velocity_and_the_default_near_it():
    position, velocity, particle_type = scene(2)
    edge_index = radius_graph(position, RADIUS)
    torch.manual_seed(0)
    still = EGNN(metadata(2), history=K, latent=16, layers=3, coordinate_gain=0.0).double()
    torch.testing.assert_close(still.next_velocity(position, velocity, particle_type, edge_index), velocity[:, -1],
                               rtol=0, atol=1e-15)
    fresh = EGNN(metadata(2), history=K, latent=16, layers=3).double()  # EGNN's gain 0.001
    change = (fresh.next_velocity(position, velocity, particle_type, edge_index) - velocity[:, -1]) / fresh.acceleration_scale
    assert 0 < change.abs().max() < 0.05


@pytest.mark.parametrize("normalise", [False, True])
def test_coincident_particles_and_resting_ones_have_finite_gradients(normalise):
    """Squared distances and sqrt(|x|^2 + eps): no NaN where x_i = x_j, v = 0 or a particle sits on a wall."""
    model = random_model(2, normalise=normalise)
    position, velocity, particle_type = scene(2)
    position[3] = torch.tensor([0.1, 0.3], dtype=torch.float64)  # on the wall: a zero wall vector
    velocity[4] = 0.0  # at rest: zero speeds
    velocity.requires_grad_(True)  # as in an unrolled loss, where the history is a prediction
    predicted = model.next_velocity(position, velocity, particle_type, radius_graph(position, RADIUS))
    predicted.pow(2).sum().backward()
    assert torch.isfinite(velocity.grad).all()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name


def layer_inputs(seed: int = 0, nodes: int = 12, channels: int = 8):
    generator = torch.Generator().manual_seed(seed)
    position = 0.4 * torch.rand(nodes, 2, generator=generator, dtype=torch.float64)  # units of R
    edge_index = radius_graph(position, 1.0)
    edge_vector = position[edge_index[1]] - position[edge_index[0]]
    h = torch.randn(nodes, channels, generator=generator, dtype=torch.float64)
    x = 0.1 * torch.randn(nodes, 2, generator=generator, dtype=torch.float64)
    velocity = torch.randn(nodes, 2, generator=generator, dtype=torch.float64)
    walls = torch.randn(nodes, 4, 2, generator=generator, dtype=torch.float64).clamp(-1, 1)
    return h, x, velocity, edge_index, edge_vector, walls, torch.zeros(2, dtype=torch.float64)


def bare_layer(channels: int = 8, **options) -> EquivariantLayer:
    """A layer with large random weights whose only vector terms are the neighbours' and the walls'."""
    torch.manual_seed(0)
    layer = EquivariantLayer(channels, coordinate_gain=1.0, **options).double()
    with torch.no_grad():
        for parameter in layer.parameters():
            parameter.mul_(20.0)
        layer.velocity_mlp[-1].weight.zero_()
        layer.velocity_mlp[-1].bias.zero_()
    return layer


def test_the_layer_is_its_equations_evaluated_neighbour_by_neighbour():
    """E-GCL with walls and gravity (rgns.nn.egnn.EquivariantLayer's docstring), by a direct loop."""
    h, x, velocity, edge_index, edge_vector, walls, _ = layer_inputs()
    gravity = torch.tensor([0.3, -0.8], dtype=torch.float64)
    layer = bare_layer()
    with torch.no_grad():
        layer.velocity_mlp[-1].weight.normal_()  # phi_v != 1 here
        new_h, u = layer(h, x, velocity, edge_index, edge_vector, walls, gravity, 0.5)
        for i in range(len(h)):
            messages, pairs = torch.zeros_like(h[i]), torch.zeros_like(x[i])
            incoming = (edge_index[1] == i).nonzero().flatten().tolist()
            for e in incoming:
                j = edge_index[0, e].item()
                relative = edge_vector[e] + x[i] - x[j]
                m = layer.edge_mlp(torch.cat([relative.pow(2).sum(0, keepdim=True),
                                              edge_vector[e].pow(2).sum(0, keepdim=True), h[i], h[j]]))
                messages, pairs = messages + m, pairs + relative * layer.coordinate_mlp(m)
            pairs = pairs / max(len(incoming), 1)  # C: the mean
            wall_messages, wall_terms = torch.zeros_like(h[i]), torch.zeros_like(x[i])
            for w in range(walls.size(1)):
                from_wall = x[i] - walls[i, w]
                m = layer.wall_mlp(torch.cat([from_wall.pow(2).sum(0, keepdim=True),
                                              walls[i, w].pow(2).sum(0, keepdim=True), h[i]]))
                wall_messages, wall_terms = wall_messages + m, wall_terms + from_wall * layer.wall_coordinate_mlp(m)
            expected_u = ((1 + layer.velocity_mlp(h[i])) * velocity[i]
                          + 0.5 * (pairs + wall_terms + layer.gravity_mlp(h[i]) * gravity))
            expected_h = h[i] + layer.node_mlp(torch.cat([h[i], messages, wall_messages]))
            torch.testing.assert_close(u[i], expected_u)
            torch.testing.assert_close(new_h[i], expected_h)


def test_tanh_bounds_the_coordinate_updates():
    h, x, velocity, edge_index, edge_vector, walls, gravity = layer_inputs()
    relative = edge_vector + x[edge_index[1]] - x[edge_index[0]]
    farthest = torch.zeros(len(h), dtype=torch.float64).scatter_reduce_(0, edge_index[1], relative.norm(dim=-1), "amax")
    bound = farthest + (x.unsqueeze(1) - walls).norm(dim=-1).sum(1)  # mean of the pairs' terms + sum of the walls'
    for tanh in (True, False):
        _, u = bare_layer(tanh=tanh)(h, x, velocity, edge_index, edge_vector, walls, gravity, 1.0)
        force = (u - velocity).norm(dim=-1)
        assert (force <= bound + 1e-12).all() == tanh  # unbounded weights break the bound without it


def test_mean_aggregation_divides_the_neighbours_term_by_the_degree():
    h, x, velocity, edge_index, edge_vector, walls, gravity = layer_inputs()
    walls = x.unsqueeze(1).expand_as(walls)  # zero wall vectors x_i - x_w: only the neighbours push
    forces = {}
    for aggregation in ("mean", "sum"):
        _, u = bare_layer(coordinate_aggregation=aggregation)(h, x, velocity, edge_index, edge_vector, walls, gravity, 1.0)
        forces[aggregation] = u - velocity
    degree = torch.bincount(edge_index[1], minlength=len(h)).clamp(min=1).to(torch.float64)
    assert (degree > 1).any()
    torch.testing.assert_close(forces["sum"], forces["mean"] * degree.unsqueeze(-1))


# ---- size and training ---------------------------------------------------------------------------

def test_the_default_size_is_the_papers():
    config = OmegaConf.load(CONFIG)
    model = instantiate(config, metadata=metadata(2))
    assert type(model) is EGNN and model.display_name == "EGNN" and not model.bidirectional
    assert math.isclose(count_parameters(model), 4.27e6, rel_tol=0.01)  # the paper's 4.27 M (WaterDrop, 2D)


@pytest.mark.parametrize("unroll", [None, {"steps": [0], "lengths": [2]}])
def test_training_steps_reach_every_parameter_and_lower_the_loss(tiny_dataset, unroll):
    windows = WindowDataset(open_split(tiny_dataset, "train"), radius=0.08, history=K, noise_std=1e-4,
                            horizon=2 if unroll else 1)
    batch = Batch.from_data_list([windows[0], windows[len(windows) - 1]])
    module = SimulatorModule({"_target_": "rgns.models.EGNN", "latent": 16, "layers": 2},
                             dict(make_metadata(), gravity=[0.0, -9.81]),
                             {"_target_": "rgns.training.losses.LossDesign", "name": "DL4"},
                             {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 3e-3},
                             noise_std=1e-4, unroll=unroll)
    module._trainer = SimpleNamespace(datamodule=SimpleNamespace(lead=0), global_step=0)  # what a step reads
    losses = train_steps(module, batch, steps=8, lr=3e-3)
    assert all(map(math.isfinite, losses)) and losses[-1] < losses[0]
