"""The faster forward step computes the old one (rgns.bench.step.reference_step) up to float32
rounding, and the rollout's neighbour list gives a fresh radius graph's edges on every step.

Tolerance (docs/benchmarks.md): positions after one step within 1e-6 of the box's side of the old
step's (float32 reassociation only). Speed is the bench's to measure, not these tests'."""
from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch

from conftest import perturb
from conftest import random_state as shared_random_state
from rgns.bench.step import reference_next_velocity, reference_step
from rgns.data.graph import NeighbourList, batched_radius_graph, radius_graph
from rgns.errors import ConfigError
from rgns.models import GNS, RGNS, State

torch.set_num_threads(1)
K = 5
TOLERANCE = 1e-6  # of the box's side, one step
ROOT = Path(__file__).resolve().parents[1]


def metadata(dim: int = 2, radius: float = 0.1) -> dict:
    return dict(bounds=[[0.1, 0.9]] * dim, default_connectivity_radius=radius, dim=dim, dt=0.0025,
                sequence_length=100, vel_mean=[1e-4] * dim, vel_std=[1e-3] * dim, acc_mean=[0.0] * dim,
                acc_std=[1e-4] * dim, gravity=[0.0, -9.81, 0.0][:dim])


def random_state(particles: int = 70, dim: int = 2, kinematic: int = 0, seed: int = 0) -> State:
    return shared_random_state(particles, dim, kinematic, seed, low=0.12, span=0.76, history=K)


def trained_like(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    return perturb(model, seed=seed).eval()


MODELS = {
    "rgns_pairwise_galilean": lambda dim: RGNS(metadata(dim), latent=16, layers=2, couplings="pairwise",
                                               galilean=True, basis="differences", hard_walls=True),
    "rgns_pairwise": lambda dim: RGNS(metadata(dim), latent=16, layers=2, couplings="pairwise"),
    "rgns_node": lambda dim: RGNS(metadata(dim), latent=16, layers=3),
    "gns_pairwise_galilean": lambda dim: GNS(metadata(dim), latent=16, layers=2, decoder="pairwise", galilean=True,
                                             hard_walls=True),
    "gns_node": lambda dim: GNS(metadata(dim), latent=16, layers=2),
}


def box_side(model) -> float:
    return float((model.bounds[:, 1] - model.bounds[:, 0]).max())


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", list(MODELS))
def test_step_is_the_old_step_up_to_float32_rounding_on_every_state_of_a_rollout(name, dim):
    model = trained_like(MODELS[name](dim))
    state = random_state(dim=dim, kinematic=4)
    neighbours = NeighbourList(model.radius, 0.2 * model.radius)
    with torch.no_grad():
        for _ in range(15):  # each state of the new rollout, stepped both ways
            new, old = model.step(state, None, neighbours), reference_step(model, state)
            difference = float((new.position - old.position).abs().max())
            assert difference < TOLERANCE * box_side(model)
            assert float((new.position - state.position).abs().max()) > 1e3 * difference  # it moved
            assert torch.equal(new.velocity_history[:, :-1], old.velocity_history[:, :-1])
            state = new


@pytest.mark.parametrize("name", ["rgns_pairwise_galilean", "gns_pairwise_galilean"])
def test_weights_changed_between_steps_are_read_again(name):
    """What a rollout computes once per weight (the ILP's pseudo-inverse, the rest frame folded
    into the first layers) follows a weight changed in place or loaded from another model."""
    model, other = trained_like(MODELS[name](2), seed=0), trained_like(MODELS[name](2), seed=1)
    state = random_state()
    edge_index = radius_graph(state.position, model.radius)
    args = (state.position, state.velocity_history, state.particle_type, edge_index)
    with torch.no_grad():
        model.next_velocity(*args)  # remembers what the weights give
        model.load_state_dict(other.state_dict())
        assert torch.allclose(model.next_velocity(*args), reference_next_velocity(other, *args), rtol=0, atol=1e-7)
        for parameter in model.parameters():
            parameter.mul_(1.1)
        assert torch.allclose(model.next_velocity(*args), reference_next_velocity(model, *args), rtol=0, atol=1e-7)
        assert not torch.allclose(model.next_velocity(*args), reference_next_velocity(other, *args), rtol=0, atol=1e-7)


@pytest.mark.parametrize("name", ["rgns_pairwise_galilean", "gns_pairwise_galilean"])
def test_gradients_reach_the_weights_as_in_the_old_step(name):
    """Training computes the reorganised layers with gradients (nothing remembered): the same
    gradients as the old arithmetic."""
    model = trained_like(MODELS[name](2))
    state = random_state()
    edge_index = radius_graph(state.position, model.radius)
    args = (state.position, state.velocity_history, state.particle_type, edge_index)
    with torch.no_grad():
        model.next_velocity(*args)  # a rollout's remembered values must not leak into training
    grads = []
    for velocity in (model.next_velocity, lambda *a: reference_next_velocity(model, *a)):
        model.zero_grad()
        (velocity(*args) / model.acc_std_noisy).pow(2).sum().backward()
        grads.append(torch.cat([p.grad.flatten() for p in model.parameters() if p.grad is not None]))
    assert grads[0].abs().max() > 0
    assert torch.allclose(grads[0], grads[1], rtol=1e-4, atol=1e-4 * float(grads[1].abs().max()))


def graph_set(edge_index: torch.Tensor) -> set[tuple[int, int]]:
    return set(map(tuple, edge_index.t().tolist()))


@pytest.mark.parametrize("dim", [2, 3])
def test_neighbour_list_is_a_fresh_radius_graph_on_every_step_of_a_rollout(dim):
    """Random motion for 60 steps, and in some steps one particle jumps by more than half the
    skin: every step's edges are a fresh radius graph's, and the jumps force a rebuild."""
    radius, skin = 0.1, 0.03
    generator = torch.Generator().manual_seed(dim)
    position = 0.1 + 0.8 * torch.rand(150, dim, generator=generator)
    neighbours = NeighbourList(radius, skin)
    reused = 0
    for step in range(60):
        builds = neighbours.builds
        edges = neighbours(position)
        assert edges.size(1) == len(graph_set(edges))  # each edge once
        assert graph_set(edges) == graph_set(radius_graph(position, radius)), step
        reused += neighbours.builds == builds
        if step % 15 == 7:  # one particle moves more than half the skin: the next call must rebuild
            builds = neighbours.builds
            position[3] += 0.6 * skin / dim**0.5
            assert graph_set(neighbours(position)) == graph_set(radius_graph(position, radius))
            assert neighbours.builds == builds + 1
        position = position + 2e-3 * torch.randn(position.shape, generator=generator)
    assert reused > 20  # the list was kept between steps


def test_neighbour_list_counts_pairs_at_exactly_the_radius_as_scipy_does():
    """A lattice of spacing R: every nearest pair lies at the radius itself."""
    radius = 0.125  # a power of two: the lattice distances are exact
    grid = torch.stack(torch.meshgrid(torch.arange(6.0), torch.arange(6.0), indexing="ij"), -1).reshape(-1, 2)
    position = (0.25 + radius * grid).float()
    edges = NeighbourList(radius, 0.05)(position)
    assert graph_set(edges) == graph_set(radius_graph(position, radius))
    assert edges.size(1) == 2 * 2 * 6 * 5  # both directions of the 60 lattice pairs


def test_neighbour_list_of_a_batch_and_its_rebuild_for_other_particles():
    generator = torch.Generator().manual_seed(0)
    position = 0.1 + 0.8 * torch.rand(90, 2, generator=generator)
    batch = torch.arange(3).repeat_interleave(30)
    neighbours = NeighbourList(0.15, 0.05)
    assert torch.equal(neighbours(position, batch).unique(dim=1),
                       batched_radius_graph(position, 0.15, batch).unique(dim=1))
    fewer = position[:60]  # other particles: a rebuild, not the old list
    assert graph_set(neighbours(fewer)) == graph_set(radius_graph(fewer, 0.15))
    assert neighbours.builds == 2
    assert graph_set(NeighbourList(0.15, 0.0)(fewer)) == graph_set(radius_graph(fewer, 0.15))  # no skin


def test_rollout_is_the_old_steps_rollout_until_the_graphs_part():
    """Over a short rollout the new steps stay within float32 rounding of the old ones."""
    model = trained_like(MODELS["rgns_pairwise_galilean"](2))
    state = random_state()
    with torch.no_grad():
        new = model.rollout(state, 5)
        old, current = [], state
        for _ in range(5):
            current = reference_step(model, current)
            old.append(current.position)
    assert float((new - torch.stack(old)).abs().max()) < 10 * TOLERANCE * box_side(model)


@pytest.mark.parametrize("name", ["rgns_pairwise_galilean", "gns_pairwise_galilean"])
def test_bfloat16_is_an_option_that_changes_only_the_products_precision(name):
    model = trained_like(MODELS[name](2))
    state = random_state()
    low = copy.deepcopy(model)
    low.precision = "bfloat16"
    with torch.no_grad():
        full, reduced = model.step(state), low.step(state)
        assert reduced.position.dtype == torch.float32
        assert torch.equal(model.step(state).position, full.position)  # the default is untouched
        change = (full.velocity_history[:, -1] - state.velocity_history[:, -1]).abs().max()
        difference = (reduced.position - full.position).abs().max()
        assert 0 < difference < change  # rounded, not another network
    low.precision = "float16"
    with pytest.raises(ConfigError, match="precision"):
        low.step(state)


@pytest.mark.parametrize("name", ["rgns", "gns"])
def test_shipped_checkpoints_step_as_before(name):
    path = ROOT / "pretrained" / "waterdrop40_main_64" / f"{name}.ckpt"
    dataset = ROOT / "datasets" / "waterdrop40_main"
    if not path.exists() or not dataset.exists():
        pytest.skip("the shipped checkpoints and their dataset are not here")
    from rgns.bench.step import start_state
    from rgns.training.module import load_simulator

    model, _ = load_simulator(str(path))
    state = start_state(str(dataset), 0, 5, model.history)
    with torch.no_grad():
        new, old = model.step(state), reference_step(model, state)
    assert float((new.position - old.position).abs().max()) < TOLERANCE * box_side(model)


def test_new_shapes_line_times_both_precisions_twice_and_counts_the_edge_counts(capsys):
    from rgns.bench.step import new_shapes

    model = trained_like(MODELS["gns_pairwise_galilean"](2))
    low = copy.deepcopy(model)
    low.precision = "bfloat16"
    state = random_state()
    new_shapes(model, low, state, 4)
    line = capsys.readouterr().out
    with torch.no_grad():
        positions, current = [], state
        for _ in range(4):
            current = model.step(current)
            positions.append(current.position)
    counts = {batched_radius_graph(p, model.radius).size(1) for p in positions}
    assert f"a rollout of 4 steps, twice ({len(counts)} distinct edge counts" in line
    assert line.count("then") == 2 and "fp32" in line and "bf16" in line
