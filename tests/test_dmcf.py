"""DMCF: the ball-to-cube map, the continuous convolution against a loop over neighbours, the
antisymmetric layer's exact momentum conservation, advection, the walls, batching and training."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from torch_geometric.data import Batch, Data

from conftest import make_metadata, train_steps
from rgns import config_dir
from rgns.data.contract import KINEMATIC, WATER
from rgns.data.graph import radius_graph
from rgns.models import DMCF, State, count_parameters
from rgns.nn.cconv import AntisymmetricConv, ContinuousConv, ball_to_cube, neighbourhood
from rgns.training.module import SimulatorModule

torch.set_num_threads(1)
SMALL = dict(latent=16, layers=2)


def metadata(dim: int = 2, **extra) -> dict:
    return make_metadata(dim=dim, radius=0.1) | extra


def ball_points(count: int, dim: int, seed: int = 0) -> torch.Tensor:
    """Uniform points inside the unit ball, float64."""
    generator = torch.Generator().manual_seed(seed)
    direction = torch.randn(count, dim, generator=generator, dtype=torch.float64)
    radius = torch.rand(count, 1, generator=generator, dtype=torch.float64) ** (1 / dim)
    return direction / direction.norm(dim=-1, keepdim=True) * radius


def randomise(module: torch.nn.Module, seed: int = 0) -> None:
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in module.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=generator, dtype=parameter.dtype))


def scene(particles: int = 60, dim: int = 2, kinematic: int = 5, seed: int = 0) -> State:
    """Particles in the lower part of the box [0.1, 0.9]^D, some of them on the floor."""
    generator = torch.Generator().manual_seed(seed)
    position = 0.12 + torch.rand(particles, dim, generator=generator) * torch.tensor([0.76] + [0.4] * (dim - 1))
    velocity = 3e-3 * torch.randn(particles, 5, dim, generator=generator)
    particle_type = torch.full((particles,), WATER)
    particle_type[particles - kinematic :] = KINEMATIC
    velocity[particle_type == KINEMATIC] = 0.0
    return State(position, velocity, particle_type)


# ---- the ball-to-cube map -------------------------------------------------------------------

@pytest.mark.parametrize("dim", [2, 3])
def test_ball_to_cube_is_odd_volume_preserving_and_onto_the_cube(dim):
    r = ball_points(400, dim)
    u = ball_to_cube(r)
    assert u.abs().max() <= 1.0 and u.abs().max() > 0.97  # into the cube, filling it
    torch.testing.assert_close(ball_to_cube(-r), -u, rtol=0, atol=0)
    # constant Jacobian: cube volume over ball volume (2D: 4 / pi; 3D: 8 / (4 pi / 3))
    expected = 4 / math.pi if dim == 2 else 6 / math.pi
    for point in r[:25]:
        jacobian = torch.autograd.functional.jacobian(lambda p: ball_to_cube(p), point)
        assert torch.linalg.det(jacobian).item() == pytest.approx(expected, rel=1e-9)
    # the unit sphere lands on the cube's surface
    surface = ball_to_cube(r / r.norm(dim=-1, keepdim=True))
    torch.testing.assert_close(surface.abs().amax(-1), torch.ones(len(r), dtype=torch.float64))


def test_ball_to_cube_has_finite_gradients_at_the_origin():
    r = torch.zeros(3, 2, dtype=torch.float64, requires_grad=True)
    ball_to_cube(r).sum().backward()
    assert torch.isfinite(r.grad).all()


# ---- the continuous convolution against a direct loop -----------------------------------------

def lookup_by_hand(r: list[float], radius: float, kernel: torch.Tensor) -> torch.Tensor:
    """Written once more, scalar by scalar: Λ(r / R), then the (bi/tri)linear interpolation of the
    grid ``kernel [K, .., K, C_in, C_out]`` (nodes on the cube's faces)."""
    x = [c / radius for c in r]
    if len(x) == 3:  # ball -> cylinder along z
        n, planar = math.sqrt(sum(c * c for c in x)), x[0] ** 2 + x[1] ** 2
        if 1.25 * x[2] ** 2 > planar:
            s = math.sqrt(3 * n / (n + abs(x[2])))
            x = [x[0] * s, x[1] * s, math.copysign(n, x[2])]
        else:
            s = n / math.sqrt(planar)
            x = [x[0] * s, x[1] * s, 1.5 * x[2]]
    a, b = x[0], x[1]  # disc -> square
    rho = math.hypot(a, b)
    if abs(a) >= abs(b):
        u = [math.copysign(rho, a), math.copysign(rho, a) * 4 / math.pi * math.atan(b / a)]
    else:
        u = [math.copysign(rho, b) * 4 / math.pi * math.atan(a / b), math.copysign(rho, b)]
    u = u + x[2:]
    k = kernel.shape[0]
    value = torch.zeros(kernel.shape[-2:], dtype=kernel.dtype)
    grid = [min(max((c + 1) / 2 * (k - 1), 0.0), k - 1) for c in u]
    lower = [min(int(math.floor(g)), k - 2) for g in grid]
    for corner in range(2 ** len(u)):
        node, weight = [], 1.0
        for d in range(len(u)):
            up = (corner >> d) & 1
            node.append(lower[d] + up)
            t = grid[d] - lower[d]
            weight *= t if up else 1 - t
        value = value + weight * kernel[tuple(node)]
    return value


@pytest.mark.parametrize("dim", [2, 3])
def test_continuous_convolution_equals_a_loop_over_neighbours(dim):
    torch.manual_seed(0)
    radius, kernel_size = 0.5, 4
    position = torch.rand(7, dim, dtype=torch.float64) * 0.8
    features = torch.randn(7, 3, dtype=torch.float64)
    conv = ContinuousConv(3, 2, dim, kernel_size).double()
    randomise(conv)
    edges = radius_graph(position, radius)
    assert 6 < edges.size(1) < 42  # some pairs in, some out
    out = conv(features, neighbourhood(position, edges, radius, kernel_size))
    for i in range(7):
        expected = features[i] @ conv.dense.weight.T + conv.dense.bias
        for j in range(7):
            r = (position[j] - position[i]).tolist()
            q = sum(c * c for c in r) / radius**2
            if j != i and q < 1:
                expected = expected + (1 - q) ** 3 * features[j] @ lookup_by_hand(r, radius, conv.kernel)
        torch.testing.assert_close(out[i], expected, rtol=1e-12, atol=1e-12)


# ---- the antisymmetric layer ----------------------------------------------------------------

@pytest.mark.parametrize("dim", [2, 3])
def test_antisymmetric_kernel_is_odd_everywhere(dim):
    conv = AntisymmetricConv(2, 3, dim, kernel_size=6).double()
    randomise(conv)
    kernel = conv.grid().reshape((6,) * dim + (2, 3))
    r = 0.99 * ball_points(50, dim)
    for point in r[:10]:
        torch.testing.assert_close(lookup_by_hand((-point).tolist(), 1.0, kernel),
                                   -lookup_by_hand(point.tolist(), 1.0, kernel), rtol=0, atol=1e-12)
    assert kernel.abs().sum() > 0 and count_parameters(conv) == 6 ** dim // 2 * 2 * 3  # half the grid learned


@pytest.mark.parametrize("dim", [2, 3])
def test_antisymmetric_layer_sums_to_zero_over_all_particles(dim):
    torch.manual_seed(1)
    position = torch.rand(40, dim, dtype=torch.float64)
    features = torch.randn(40, 5, dtype=torch.float64)
    lookups = neighbourhood(position, radius_graph(position, 0.4), 0.4, 8)
    conv = AntisymmetricConv(5, dim, dim).double()
    randomise(conv)
    out = conv(features, lookups)
    assert out.abs().mean() > 1e-2
    assert out.sum(0).abs().max() < 1e-12 * out.abs().sum()
    plain = ContinuousConv(5, dim, dim, dense=False).double()  # the check can fail: a plain kernel does not
    randomise(plain)
    assert plain(features, lookups).sum(0).abs().max() > 1e-3


@pytest.mark.parametrize("dim", [2, 3])
def test_corrections_sum_to_zero_over_fluid_and_boundary_particles(dim):
    """The whole network, random weights and inputs in float64: momentum is conserved exactly."""
    model = DMCF(metadata(dim), **SMALL).double()
    randomise(model)
    state = scene(dim=dim)
    velocity = state.velocity_history[:, -1].double()
    fluid, walls = model.correction(state.position.double() + velocity, velocity, state.particle_type)
    assert len(walls) > 0 and fluid.abs().mean() > 0 and walls.abs().mean() > 0
    total = fluid.sum(0) + walls.sum(0)
    assert total.abs().max() < 1e-12 * (fluid.abs().sum() + walls.abs().sum())
    assert fluid.sum(0).abs().max() > 1e-6 * fluid.abs().sum()  # the walls take the reaction


# ---- the step ---------------------------------------------------------------------------------

def test_next_velocity_is_advection_under_gravity_plus_the_correction():
    model = DMCF(metadata(gravity=[0.0, -9.81]), **SMALL)
    torch.testing.assert_close(model.gravity, torch.tensor([0.0, -9.81 * 0.0025**2]))
    assert DMCF(metadata(), **SMALL).gravity[1] == model.gravity[1]  # no metadata gravity: the default
    assert DMCF(metadata(gravity=[0.0, -1.0]), **SMALL).gravity[1] == pytest.approx(-0.0025**2)
    state = scene()
    args = (state.position, state.velocity_history, state.particle_type, None)
    velocity = state.velocity_history[:, -1] + model.gravity
    correction, _ = model.correction(state.position + velocity, velocity, state.particle_type)
    torch.testing.assert_close(model.next_velocity(*args), velocity + correction)
    with torch.no_grad():
        model.decoder.half_kernel.zero_()
    torch.testing.assert_close(model.next_velocity(*args), velocity, rtol=0, atol=0)  # ballistic


def test_ablations_read_the_scene_at_the_current_positions_and_drop_the_momentum_balance():
    """advect=False reads the scene at x^t (same inputs v*); antisymmetric=False ends in an
    ordinary continuous convolution, whose corrections no longer sum to zero."""
    torch.manual_seed(0)
    state = scene()
    args = (state.position, state.velocity_history, state.particle_type, None)
    velocity = state.velocity_history[:, -1]
    still = DMCF(metadata(), **SMALL, advect=False)
    randomise(still)
    velocity = velocity + still.gravity
    correction, _ = still.correction(state.position, velocity, state.particle_type)
    torch.testing.assert_close(still.next_velocity(*args), velocity + correction)
    moved, _ = still.correction(state.position + velocity, velocity, state.particle_type)
    assert not torch.allclose(moved, correction)  # where the scene is read matters
    plain = DMCF(metadata(), **SMALL, antisymmetric=False).double()
    randomise(plain)
    assert not hasattr(plain.decoder, "half_kernel")
    fluid, walls = plain.correction(state.position.double() + velocity.double(), velocity.double(),
                                    state.particle_type)
    total = fluid.sum(0) + walls.sum(0)
    assert total.abs().max() > 1e-3 * (fluid.abs().sum() + walls.abs().sum())


@pytest.mark.parametrize("dim", [2, 3])
def test_walls_are_sampled_on_the_faces_near_the_particles(dim):
    model = DMCF(metadata(dim), wall_spacing=0.05, **SMALL)
    walls, normals = model.wall_position, model.wall_normal
    faces = 2 * dim * 16 ** (dim - 1)  # 0.8 / 0.05 = 16 samples per face and axis
    assert walls.shape == normals.shape == (faces, dim)
    on_lower = torch.isclose(walls, torch.tensor(0.1)) & (normals == 1)
    on_upper = torch.isclose(walls, torch.tensor(0.9)) & (normals == -1)
    assert ((on_lower | on_upper).sum(-1) == 1).all()  # each on one face, its normal into the box
    assert len(torch.unique(walls, dim=0)) == faces  # no sample shared by two faces
    position = torch.full((2, dim), 0.5)
    position[0, 1] = 0.15  # near the floor only
    kept, kept_normals, _ = model.boundary_particles(position, None)
    distance = torch.cdist(walls.double(), position.double()).min(1).values
    assert len(kept) == int((distance < model.conv_radius).sum()) > 0
    assert (kept_normals[:, 1] == 1).all()


def test_wall_spacing_is_the_datasets_particle_spacing():
    generated = metadata(generator={"params": {"spacing": 0.04}})
    assert DMCF(generated, **SMALL).wall_spacing == 0.04
    # as train.py builds it: Hydra has instantiated the scene the params describe
    assert DMCF(metadata(generator={"params": SimpleNamespace(spacing=0.04)}), **SMALL).wall_spacing == 0.04
    assert DMCF(metadata(), **SMALL).wall_spacing == 0.05  # none known: half the connectivity radius


def test_graphs_of_a_batch_do_not_interact():
    model = DMCF(metadata(), **SMALL)
    randomise(model)
    first, second = scene(seed=0), scene(particles=50, seed=1)
    second.position[:, 0] += 0.01  # overlapping boxes, different particles
    batch = torch.cat([torch.zeros(60, dtype=torch.long), torch.ones(50, dtype=torch.long)])
    both = model.next_velocity(torch.cat([first.position, second.position]),
                               torch.cat([first.velocity_history, second.velocity_history]),
                               torch.cat([first.particle_type, second.particle_type]), None, batch)
    for part, state in zip(both.split([60, 50]), (first, second)):
        alone = model.next_velocity(state.position, state.velocity_history, state.particle_type, None)
        torch.testing.assert_close(part, alone, rtol=1e-5, atol=1e-9)


def test_paper_size():
    """The default: 2.26 M parameters in 2D against the paper's 2.17 M (conf/model/dmcf.yaml)."""
    count = count_parameters(DMCF(metadata()))
    assert count == 2_262_384
    assert abs(count / 2.17e6 - 1) < 0.05


# ---- training ----------------------------------------------------------------------------------

MODEL = {"_target_": "rgns.models.DMCF", "latent": 16, "layers": 2, "hard_walls": True}
LOSS = {"_target_": "rgns.training.losses.LossDesign", "name": "DL4"}
OPTIMIZER = {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 3e-3}


def training_batch(horizon: int = 0) -> Batch:
    """Windows of a free fall (``v^{t+1} = v^t + g``): DMCF must learn to leave the advection uncorrected."""
    samples = []
    for g in range(2):
        state = scene(particles=40, seed=g)
        velocity = state.velocity_history
        target = velocity[:, -1] + torch.tensor([0.0, -9.81 * 0.0025**2])
        target[state.particle_type == KINEMATIC] = 0.0
        frames = state.position.unsqueeze(1) + target.unsqueeze(1) * torch.arange(-5, horizon + 1).view(1, -1, 1)
        samples.append(Data(pos=state.position, edge_index=radius_graph(state.position, 0.1),
                            particle_type=state.particle_type, forward_input=velocity, forward_target=target,
                            frames=frames))
    return Batch.from_data_list(samples)


def test_training_steps_lower_the_loss_with_finite_gradients_everywhere():
    torch.manual_seed(0)
    module = SimulatorModule(MODEL, metadata(), LOSS, OPTIMIZER, noise_std=0.0)
    assert not module.train_inverse and not module.model.bidirectional
    losses = train_steps(module, training_batch(), steps=8, lr=3e-3)
    assert losses[-1] < 0.8 * losses[0]


def test_unrolled_training_backpropagates_through_the_steps():
    """recipe=unroll: the loss through 3 DMCF steps, gradients through all of them."""
    module = SimulatorModule(MODEL, metadata(), LOSS, OPTIMIZER, noise_std=1e-4, unroll={"steps": [0], "lengths": [3]})
    module._trainer = SimpleNamespace(datamodule=SimpleNamespace(lead=0), global_step=1)
    terms = module._losses(training_batch(horizon=3))
    terms["loss"].backward()
    for name, parameter in module.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name


def test_config_composes_with_the_main_preset(tmp_path):
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        cfg = compose("train", overrides=[f"output_dir={tmp_path}", "experiment=main", "model=dmcf"])
    assert (cfg.model.latent, cfg.model.layers, cfg.model.hard_walls) == (32, 2, True)
    model = instantiate(cfg.model, metadata=metadata(), history=cfg.history, noise_std=cfg.noise_std)
    assert type(model) is DMCF and model.hard_walls and model.display_name == "DMCF"
