"""The simulators: the training contract, exactness of the physical inverse, parameter counts,
memory saving, rollouts and kinematic particles."""
from __future__ import annotations

import pytest
import torch
from torch_geometric.data import Batch, Data

from rgns.data.contract import KINEMATIC, WATER
from rgns.data.graph import edge_channels, edge_features, edge_union, radius_graph, reverse_edges, wall_distance, wall_gate
from rgns.models import GNS, RGNS, SepGNS, State, count_parameters

torch.set_num_threads(1)
K = 5
SMALL = dict(latent=16, layers=2)


def metadata(dim: int = 2, radius: float = 0.1) -> dict:
    return dict(bounds=[[0.1, 0.9]] * dim, default_connectivity_radius=radius, dim=dim, dt=0.0025,
                sequence_length=100, vel_mean=[1e-4] * dim, vel_std=[1e-3] * dim, acc_mean=[0.0] * dim,
                acc_std=[1e-4] * dim)


def random_state(particles: int = 80, dim: int = 2, kinematic: int = 8, seed: int = 0, graphs: int = 1) -> State:
    """A state in the box: Brownian velocities, the last ``kinematic`` particles of each graph static."""
    generator = torch.Generator().manual_seed(seed)
    position = 0.15 + 0.7 * torch.rand(graphs * particles, dim, generator=generator)
    velocity = 2e-3 * torch.randn(graphs * particles, K, dim, generator=generator)
    particle_type = torch.full((particles,), WATER)
    particle_type[particles - kinematic:] = KINEMATIC
    particle_type = particle_type.repeat(graphs)
    velocity[particle_type == KINEMATIC] = 0.0
    batch = torch.arange(graphs).repeat_interleave(particles) if graphs > 1 else None
    return State(position, velocity, particle_type, batch)


def perturb(module: torch.nn.Module, scale: float = 0.1, seed: int = 0) -> None:
    """Move every parameter off its initialisation (R-GNS starts as the identity map)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in module.parameters():
            parameter.add_(scale * torch.randn(parameter.shape, generator=generator))


def training_batch(dim: int = 2, graphs: int = 2, seed: int = 0) -> Batch:
    """A batch with the fields rgns.data.windows produces."""
    samples = []
    for g in range(graphs):
        state = random_state(particles=40 + 10 * g, dim=dim, seed=seed + g)
        velocity = state.velocity_history
        samples.append(Data(pos=state.position, edge_index=radius_graph(state.position, 0.1),
                            particle_type=state.particle_type, forward_input=velocity,
                            forward_target=velocity[:, -1] + 1e-4, inverse_input=torch.roll(velocity, -1, 1),
                            inverse_target=velocity[:, 0] - 1e-4))
    return Batch.from_data_list(samples)


# ---- the contract with training ---------------------------------------------------------------

@pytest.mark.parametrize("cls,options", [(GNS, {}), (RGNS, {}), (SepGNS, {}), (GNS, dict(edge_velocity=True)),
                                         (RGNS, dict(edge_velocity=True)), (GNS, dict(decoder="pairwise")),
                                         (GNS, dict(decoder="pairwise", galilean=True)),
                                         (RGNS, dict(couplings="pairwise"))])
@pytest.mark.parametrize("dim", [2, 3])
def test_contract_on_a_training_batch(cls, options, dim):
    torch.manual_seed(0)
    model = cls(metadata(dim), history=K, **SMALL, **options)
    perturb(model)
    assert model.history == K and model.radius == 0.1 and model.acc_std_noisy.shape == (dim,)
    assert cls.bidirectional == (cls is not GNS)
    batch = training_batch(dim)
    args = (batch.pos, batch.forward_input, batch.particle_type, batch.edge_index, batch.batch)
    forward_input = batch.forward_input.clone()
    prediction = model.next_velocity(*args)
    assert prediction.shape == batch.forward_target.shape
    fluid = batch.particle_type != KINEMATIC
    loss = (((prediction - batch.forward_target) / model.acc_std_noisy)[fluid] ** 2).mean()
    if model.bidirectional:
        inverse = model.oldest_velocity(batch.pos, batch.inverse_input, batch.particle_type, batch.edge_index,
                                        batch.batch)
        assert inverse.shape == batch.inverse_target.shape
        loss = loss + (((inverse - batch.inverse_target) / model.acc_std_noisy)[fluid] ** 2).mean()
    else:
        with pytest.raises(NotImplementedError):
            model.oldest_velocity(*args)
    loss.backward()
    assert torch.equal(batch.forward_input, forward_input)  # inputs are left intact (memory saving)
    assert torch.isfinite(loss)
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0, name


def test_graphs_of_a_batch_do_not_interact():
    torch.manual_seed(0)
    model = RGNS(metadata(), **SMALL)
    perturb(model)
    batch = training_batch(graphs=2)
    both = model.next_velocity(batch.pos, batch.forward_input, batch.particle_type, batch.edge_index, batch.batch)
    first = batch.get_example(0)
    alone = model.next_velocity(first.pos, first.forward_input, first.particle_type, first.edge_index)
    torch.testing.assert_close(both[: first.num_nodes], alone, rtol=0, atol=1e-6)


def test_rgns_starts_as_constant_velocity_in_both_directions():
    model = RGNS(metadata(), history=K, **SMALL)
    state = random_state()
    edge_index = radius_graph(state.position, model.radius)
    args = (state.position, state.velocity_history, state.particle_type, edge_index)
    torch.testing.assert_close(model.next_velocity(*args), state.velocity_history[:, -1], rtol=0, atol=1e-8)
    torch.testing.assert_close(model.oldest_velocity(*args), state.velocity_history[:, 0], rtol=0, atol=1e-8)


def away_from_walls(position: torch.Tensor) -> torch.Tensor:
    """``[N]``: the particles farther than R (0.1) from every wall of the unit box."""
    return ((position - 0.1 > 0.1) & (0.9 - position > 0.1)).all(-1)


def boost_case(dim: int):
    """A fluid-only state in float64 (positions, velocity history, types), the particles away
    from the walls, and a boost ``u`` of about 2x the velocity std: the rest-frame tests' case."""
    state = random_state(dim=dim, seed=3, kinematic=0)
    position = state.position.double()
    u = torch.linspace(2e-3, -3e-3, dim, dtype=torch.float64)
    return position, state.velocity_history.double(), state.particle_type, away_from_walls(position), u


def gravity_metadata(dim: int = 2) -> dict:
    return dict(metadata(dim), gravity=[0.0] * (dim - 1) + [-9.81])  # 6.1e-5 per frame^2 at dt = 0.0025


def test_rgns_with_known_gravity_starts_as_ballistic_motion_in_both_directions():
    model = RGNS(gravity_metadata(), history=K, known_gravity=True, **SMALL)
    g = torch.tensor([0.0, -9.81 * 0.0025**2])
    state = random_state()
    edge_index = radius_graph(state.position, model.radius)
    args = (state.position, state.velocity_history, state.particle_type, edge_index)
    torch.testing.assert_close(model.next_velocity(*args), state.velocity_history[:, -1] + g, rtol=0, atol=1e-8)
    torch.testing.assert_close(model.oldest_velocity(*args), state.velocity_history[:, 0] - g, rtol=0, atol=1e-8)
    batch = training_batch()
    forward, inverse = model.both_velocities(batch.pos, batch.forward_input, batch.inverse_input, batch.particle_type,
                                             batch.edge_index, batch.batch)
    torch.testing.assert_close(forward, batch.forward_input[:, -1] + g, rtol=0, atol=1e-8)
    torch.testing.assert_close(inverse, batch.inverse_input[:, 0] - g, rtol=0, atol=1e-8)
    plain = RGNS(metadata(), history=K, **SMALL)  # the option changes nothing else: same parameters, same checkpoints
    assert list(plain.state_dict()) == list(model.state_dict())


@pytest.mark.parametrize("cls", [GNS, SepGNS])
def test_gns_with_known_gravity_predicts_acceleration_beyond_gravity(cls):
    """A zero decoder output is free fall (known_gravity) or the dataset's mean acceleration."""
    state = random_state()
    edge_index = radius_graph(state.position, 0.1)
    args = (state.position, state.velocity_history, state.particle_type, edge_index)
    for known, acceleration in ((True, torch.tensor([0.0, -9.81 * 0.0025**2])), (False, torch.zeros(2))):
        model = cls(gravity_metadata(), history=K, known_gravity=known, **SMALL)
        gns = [model] if cls is GNS else [model.forward_gns, model.backward_gns]
        for network in gns:
            torch.nn.init.zeros_(network.decoder[-1].weight)
            torch.nn.init.zeros_(network.decoder[-1].bias)
        torch.testing.assert_close(model.next_velocity(*args), state.velocity_history[:, -1] + acceleration,
                                   rtol=0, atol=1e-9)
        if cls is SepGNS:  # backwards in time gravity keeps its sign: v^{t-k+1} = v^{t-k+2} - g
            torch.testing.assert_close(model.oldest_velocity(*args), state.velocity_history[:, 0] - acceleration,
                                       rtol=0, atol=1e-9)


def test_rgns_forward_only_training_trains_the_same_network():
    """R-GNS† is a training option: the forward loss alone reaches every parameter."""
    model = RGNS(metadata(), **SMALL)
    perturb(model)
    batch = training_batch()
    model.next_velocity(batch.pos, batch.forward_input, batch.particle_type, batch.edge_index).sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())


# ---- exactness --------------------------------------------------------------------------------

@pytest.mark.parametrize("history", [1, 4, 5, 6])
def test_difference_basis_is_an_exact_change_of_basis(history):
    """basis="differences": the middle velocity over the velocity std, the other slots as
    accelerations over the acceleration std; decoding inverts it, and the identity latent map
    is still constant velocity."""
    model = RGNS(metadata(2), history=history, latent=16, layers=2, basis="differences")
    velocity = torch.randn(9, history, 2, dtype=torch.float64) * 1e-3
    model = model.double()
    x = model.to_basis(velocity)
    c = history // 2
    torch.testing.assert_close(x[:, c], (velocity[:, c] - model.vel_mean) / model.vel_std_noisy)
    if history > c + 1:
        torch.testing.assert_close(x[:, -1], (velocity[:, -1] - velocity[:, -2]) / model.acc_std_noisy)
    if c > 0:
        torch.testing.assert_close(x[:, 0], (velocity[:, 1] - velocity[:, 0]) / model.acc_std_noisy)
    torch.testing.assert_close(model.from_basis(x), velocity, rtol=0, atol=1e-15)
    state = random_state(dim=2, seed=1)
    model = RGNS(metadata(2), latent=16, layers=2, basis="differences")  # zero-initialised couplings
    with torch.no_grad():
        assert torch.allclose(model.step(state).velocity_history[:, -1], state.velocity_history[:, -1], atol=1e-9)


@pytest.mark.parametrize("history", [1, 5])
def test_gns_difference_basis_reads_the_newest_velocity_and_accelerations(history):
    """GNS with basis="differences": its node encoder reads v^{k-1} over the velocity std and the
    k - 1 accelerations over the acceleration std, in place of the k normalised velocities."""
    model = GNS(metadata(2), history=history, latent=16, layers=2, basis="differences").double()
    velocity = torch.randn(9, history, 2, dtype=torch.float64) * 1e-3
    seen = {}
    model.node_encoder.register_forward_hook(lambda module, args, out: seen.update(x=args[0]))
    position = torch.rand(9, 2, dtype=torch.float64) * 0.8 + 0.1
    model.next_velocity(position, velocity, torch.full((9,), WATER), radius_graph(position, 0.2))
    features = seen["x"][:, : history * 2].unflatten(1, (history, 2))
    torch.testing.assert_close(features[:, -1], (velocity[:, -1] - model.vel_mean) / model.vel_std_noisy)
    if history > 1:
        torch.testing.assert_close(features[:, 0], (velocity[:, 1] - velocity[:, 0]) / model.acc_std_noisy)
    torch.testing.assert_close(model.from_differences(features, history - 1), velocity, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="basis"):
        GNS(metadata(2), basis="accelerations")


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("encoder", ["ilp", "mlp"])
@pytest.mark.parametrize("basis", ["velocity", "differences"])
@pytest.mark.parametrize("known_gravity", [False, True])
def test_inverse_step_recovers_position_and_known_history_exactly(dim, encoder, basis, known_gravity):
    torch.manual_seed(dim)
    model = RGNS(gravity_metadata(dim), latent=16, layers=10, encoder=encoder, basis=basis, known_gravity=known_gravity)
    perturb(model, seed=dim)
    state = random_state(dim=dim, seed=dim)
    back = model.inverse_step(model.step(state))
    torch.testing.assert_close(back.position, state.position, rtol=0, atol=1e-6)  # p^t = p^{t+1} - v^{t+1}
    assert torch.equal(back.velocity_history[:, 1:], state.velocity_history[:, 1:])  # the masked slots


def test_edge_features_read_the_relative_velocity_and_how_fast_a_pair_closes_in():
    position = torch.tensor([[0.0, 0.0], [0.05, 0.0], [0.0, 0.08]])
    velocity = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [1.0, 3.0]]) * 1e-3  # 0 and 1 approach, 2 rises away from 0
    edge_index = torch.tensor([[1, 0, 2], [0, 1, 0]])  # senders, receivers
    assert edge_features(position, edge_index, 0.1).shape == (3, edge_channels(2))
    features = edge_features(position, edge_index, 0.1, velocity, torch.tensor([1e-3, 2e-3]))  # [E, 2D + 2]
    assert features.shape == (3, edge_channels(2, velocity=True)) == (3, 6)
    torch.testing.assert_close(features[:, :3], edge_features(position, edge_index, 0.1))  # geometry as before
    torch.testing.assert_close(features[:, 2:5], torch.tensor([[0.5, -2.0, 0.0], [0.5, 2.0, 0.0], [0.8, 0.0, 1.5]]))
    # along the edge: negative when the pair closes in (either direction of the edge), positive when it separates
    torch.testing.assert_close(features[:, 5], torch.tensor([-2.0, -2.0, 1.5]))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("edge_velocity", [False, True])
def test_gns_pairwise_decoder_conserves_momentum_away_from_the_walls(dim, edge_velocity):
    """decoder="pairwise": antisymmetrised pair terms cancel in the sum over the particles; only
    particles within R of a wall add a term of their own; the reference is gravity."""
    model = GNS(gravity_metadata(dim), decoder="pairwise", edge_velocity=edge_velocity, **SMALL).double()
    assert model.known_gravity and model.gravity_reference[-1] < 0
    perturb(model, seed=dim)
    state = random_state(dim=dim, seed=dim, kinematic=0)
    position, history = state.position.double(), state.velocity_history.double()
    edge_index = radius_graph(position, model.radius)
    inside = away_from_walls(position)
    acceleration = model.next_velocity(position, history, state.particle_type, edge_index) - history[:, -1]
    gravity = model.gravity_reference.double()
    excess = (acceleration - gravity) / model.acc_std_noisy.double()  # [N, D]
    assert excess.abs().mean() > 1e-3
    # away from the walls only pair terms: their sum over the particles is zero
    core = inside.nonzero().squeeze(-1)
    keep = inside[edge_index].all(0)  # the graph of the inner particles alone
    relabel = torch.full((len(position),), -1, dtype=torch.long)
    relabel[core] = torch.arange(len(core))
    inner = model.next_velocity(position[core], history[core], state.particle_type[core], relabel[edge_index[:, keep]])
    total = ((inner - history[core, -1] - gravity) / model.acc_std_noisy.double()).sum(0)
    assert total.abs().max() < 1e-10 * excess.abs().sum()
    # with particles at the walls the sum is no longer zero: the walls take the reaction
    assert excess.sum(0).abs().max() > 1e-6 * excess.abs().sum()
    with pytest.raises(ValueError, match="decoder"):
        GNS(metadata(dim), decoder="edge", **SMALL)


@pytest.mark.parametrize("dim, density_condition, galilean", [(2, False, False), (3, False, False), (2, True, False),
                                                               (2, False, True), (3, True, True)])
def test_rgns_pairwise_couplings_conserve_momentum_away_from_the_walls_in_both_directions(dim, density_condition,
                                                                                         galilean):
    """couplings="pairwise": the velocities' sum over the particles changes by gravity alone,
    forward and backward in time, where no particle is within R of a wall; not so near a wall.
    The density condition (symmetric in the pair's ends) and the rest frames (each pair term
    still antisymmetrised) keep it so, and the inverse step stays exact."""
    model = RGNS(gravity_metadata(dim), latent=16, layers=3, basis="differences", couplings="pairwise",
                 density_condition=density_condition, galilean=galilean).double()
    assert model.known_gravity  # implied
    perturb(model, seed=dim)
    state = random_state(dim=dim, seed=dim, kinematic=0)
    position, history = state.position.double(), state.velocity_history.double()
    gravity = model.gravity_shift.double()
    inside = away_from_walls(position)
    core = inside.nonzero().squeeze(-1)
    relabel = torch.full((len(position),), -1, dtype=torch.long)
    relabel[core] = torch.arange(len(core))
    full_graph = radius_graph(position, model.radius)
    inner_graph = relabel[full_graph[:, inside[full_graph].all(0)]]
    for graph, index, conserved in ((inner_graph, core, True), (full_graph, torch.arange(len(position)), False)):
        p, v, t = position[index], history[index], state.particle_type[index]
        forward = model.next_velocity(p, v, t, graph) - v[:, -1] - gravity  # [N, D]
        backward = model.oldest_velocity(p, v, t, graph) - v[:, 0] + gravity  # one step further back
        for change in (forward, backward):
            scale = change.abs().sum()
            assert scale > 1e-6
            if conserved:
                assert change.sum(0).abs().max() < 1e-9 * scale
            else:  # the walls take the reaction
                assert change.sum(0).abs().max() > 1e-6 * scale
    state = State(position, history, state.particle_type)
    back = model.inverse_step(model.step(state))  # still the exact inverse where it is exact
    torch.testing.assert_close(back.position, state.position, rtol=0, atol=1e-12)
    assert torch.equal(back.velocity_history[:, 1:], state.velocity_history[:, 1:])
    with pytest.raises(ValueError, match="couplings"):
        RGNS(gravity_metadata(dim), couplings="edges", **SMALL)


@pytest.mark.parametrize("dim, basis", [(2, "differences"), (3, "differences"), (2, "velocity")])
def test_galilean_pair_terms_read_relative_motion_only(dim, basis):
    """galilean=True: away from the walls, moving every velocity of the history by the same u moves
    both directions' predictions by u and nothing else (to round-off); without it, or within R of
    a wall (whose term reads the absolute velocity), it does not."""
    position, history, types, inside, u = boost_case(dim)
    gaps = {}
    for galilean in (True, False):
        model = RGNS(gravity_metadata(dim), latent=16, layers=3, basis=basis, couplings="pairwise",
                     galilean=galilean).double()
        perturb(model, seed=dim)
        for name, index in (("inside", inside.nonzero().squeeze(-1)), ("all", torch.arange(len(position)))):
            p, v, t = position[index], history[index], types[index]
            graph = radius_graph(p, model.radius)
            for direction in (model.next_velocity, model.oldest_velocity):
                with torch.no_grad():
                    plain, moved = direction(p, v, t, graph), direction(p, v + u, t, graph)
                scale = (plain - v[:, -1]).abs().max()  # the size of the network's change
                gaps[galilean, name, direction.__name__] = float((moved - plain - u).abs().max() / scale)
    for direction in ("next_velocity", "oldest_velocity"):
        assert gaps[True, "inside", direction] < 1e-10
        assert gaps[True, "all", direction] > 1e-4  # the wall term sees the boost
        assert gaps[False, "inside", direction] > 1e-4
    with pytest.raises(ValueError, match="galilean"):
        RGNS(gravity_metadata(dim), galilean=True, **SMALL)  # node couplings
    with pytest.raises(ValueError, match="galilean"):
        RGNS(gravity_metadata(dim), galilean=True, couplings="pairwise", encoder="mlp", **SMALL)


@pytest.mark.parametrize("dim", [2, 3])
def test_gns_galilean_pair_terms_read_relative_motion_only(dim):
    """GNS galilean=True (pairwise decoder): away from the walls, moving every velocity of the
    history by the same u moves the predicted velocity by u and nothing else (to round-off);
    without it, or within R of a wall (whose term reads the absolute velocity), it does not. The
    pair terms still cancel in the sum over the particles."""
    position, history, types, inside, u = boost_case(dim)
    gaps = {}
    for galilean in (True, False):
        model = GNS(gravity_metadata(dim), decoder="pairwise", galilean=galilean, **SMALL).double()
        assert model.edge_velocity == galilean  # implied by galilean, off by default
        perturb(model, seed=dim)
        for name, index in (("inside", inside.nonzero().squeeze(-1)), ("all", torch.arange(len(position)))):
            p, v, t = position[index], history[index], types[index]
            graph = radius_graph(p, model.radius)
            with torch.no_grad():
                plain, moved = model.next_velocity(p, v, t, graph), model.next_velocity(p, v + u, t, graph)
            change = plain - v[:, -1] - model.gravity_reference.double()  # the network's share of the step
            assert change.abs().max() > 1e-6
            if galilean and name == "inside":  # pair terms alone: they sum to zero
                assert change.sum(0).abs().max() < 1e-9 * change.abs().sum()
            gaps[galilean, name] = float((moved - plain - u).abs().max() / change.abs().max())
    assert gaps[True, "inside"] < 1e-10
    assert gaps[True, "all"] > 1e-4  # the wall term sees the boost
    assert gaps[False, "inside"] > 1e-4
    with pytest.raises(ValueError, match="galilean"):
        GNS(gravity_metadata(dim), galilean=True, **SMALL)  # node decoder


def test_density_condition_starts_as_the_network_without_it_then_reads_each_ends_density():
    """The density map starts at zero: with the weights of a model without it, the same steps.
    Moved off zero, the step changes, and the edge latent moves by the map of both ends' kernel
    densities, counted here by hand."""
    plain = RGNS(gravity_metadata(2), couplings="pairwise", **SMALL).double()
    perturb(plain, seed=5)
    dense = RGNS(gravity_metadata(2), couplings="pairwise", density_condition=True, **SMALL).double()
    missing, unexpected = dense.load_state_dict(plain.state_dict(), strict=False)
    assert set(missing) == dense.warm_start_optional() == {"density_encoder.weight"} and not unexpected
    assert plain.warm_start_optional() == set()
    state = random_state(kinematic=0)
    position, history, types = state.position.double(), state.velocity_history.double(), state.particle_type
    graph = radius_graph(position, plain.radius)
    before = plain.next_velocity(position, history, types, graph)
    torch.testing.assert_close(dense.next_velocity(position, history, types, graph), before, rtol=0, atol=0)
    with torch.no_grad():
        dense.density_encoder.weight.normal_(generator=torch.Generator().manual_seed(6))
    after = dense.next_velocity(position, history, types, graph)
    assert (after - before).abs().max() > 1e-3 * (before - history[:, -1]).abs().max()
    # the edge latent moves by the map of [density of the receiver, density of the sender], each less its own 1
    edge_latent, _ = dense.conditions(position, types, graph)
    plain_latent, _ = plain.conditions(position, types, graph)
    sender, receiver = graph
    count = torch.zeros(len(position), dtype=torch.float64)
    for j, i in graph.T.tolist():  # by hand: (1 - r^2/R^2)^3 per neighbour
        count[i] += (1 - (position[j] - position[i]).pow(2).sum() / plain.radius**2) ** 3
    shift = torch.stack([count[receiver], count[sender]], dim=-1) @ dense.density_encoder.weight.T
    torch.testing.assert_close(edge_latent - plain_latent, shift)


def test_gns_pairwise_decoder_is_psi_on_the_edge_less_psi_on_its_reverse():
    """The decoder evaluates psi once per directed edge and pairs each edge with its reverse; that
    is the definition, psi(h_i, h_j, g_ij) - psi(h_j, h_i, g_ji), evaluated on both directions."""
    model = GNS(gravity_metadata(2), decoder="pairwise", **SMALL).double()
    perturb(model, seed=4)
    state = random_state(seed=4, kinematic=0)
    position, history = state.position.double(), state.velocity_history.double()
    edge_index = radius_graph(position, model.radius)
    geometry = model.geometry(position, history, edge_index)
    nodes, edges = model.encode(position, history, state.particle_type, geometry)
    x = model.process(nodes, edge_index, edges)
    sender, receiver = edge_index
    flipped = model.geometry(position, history, edge_index.flip(0))  # g_ji, computed from the positions
    pair = (model.decoder(torch.cat([x[receiver], x[sender], geometry], -1))
            - model.decoder(torch.cat([x[sender], x[receiver], flipped], -1)))  # [E, D]
    assert pair.abs().max() > 1e-3
    walls = wall_distance(position, model.bounds, model.radius)
    near = (1 - walls.min(dim=-1, keepdim=True).values).clamp(0, 1)
    want = ((torch.zeros_like(position).index_add_(0, receiver, pair) + near * model.wall_decoder(x))
            * model.acc_std_noisy.double() + model.gravity_reference.double())
    torch.testing.assert_close(model.decode(x, position, edge_index, geometry), want, rtol=0, atol=1e-12)


def test_wall_gate_is_one_at_a_wall_and_falls_to_zero_at_r_from_the_nearest():
    bounds = torch.tensor([[0.0, 1.0], [0.0, 2.0]])
    position = torch.tensor([[0.0, 1.0], [0.05, 1.0], [0.5, 1.99], [0.5, 1.0], [1.2, 1.0]])  # R = 0.1
    gate = wall_gate(wall_distance(position, bounds, 0.1))
    torch.testing.assert_close(gate[:, 0], torch.tensor([1.0, 0.5, 0.9, 0.0, 1.0]))  # outside: 1


def test_reverse_edges_pairs_every_edge_with_its_reverse():
    edge_index = radius_graph(random_state(seed=3).position, 0.1)
    assert edge_index.size(1) > 0
    reverse = reverse_edges(edge_index, 80)
    assert torch.equal(edge_index[:, reverse], edge_index.flip(0))
    with pytest.raises(ValueError, match="reverse"):
        reverse_edges(edge_index[:, 1:], 80)  # one edge lost its partner


def test_edge_union_holds_each_edge_of_either_graph_once_in_sorted_order():
    before = random_state(seed=3).position
    after = before + 0.02 * torch.randn(before.shape, generator=torch.Generator().manual_seed(4))
    first, second = radius_graph(before, 0.1), radius_graph(after, 0.1)
    union = edge_union(first, second, len(before))
    assert torch.equal(union, torch.cat([first, second], dim=1).unique(dim=1))
    assert first.size(1) < union.size(1) < first.size(1) + second.size(1)  # shared edges, and edges of one only
    assert torch.equal(edge_union(first, first, len(before)), first.unique(dim=1))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("known_gravity", [False, True])
def test_rgns_edge_velocity_conditions_are_the_same_in_both_directions(dim, known_gravity, monkeypatch):
    """With edge_velocity, a step and its inverse read v^t (the newest slot of V^t, the second
    newest of V^{t+1}) and so build the same conditions; the inverse stays exact where it is."""
    torch.manual_seed(dim)
    model = RGNS(gravity_metadata(dim), latent=16, layers=4, basis="differences", known_gravity=known_gravity,
                 edge_velocity=True)
    perturb(model, seed=dim)
    seen = []
    conditions = model.conditions
    monkeypatch.setattr(model, "conditions", lambda *args: seen.append(conditions(*args)) or seen[-1])
    state = random_state(dim=dim, seed=dim)
    back = model.inverse_step(model.step(state))
    (forward_edges, forward_nodes), (inverse_edges, inverse_nodes) = seen
    # equal up to float32 rounding: the inverse recomputes p^t as p^{t+1} - v^{t+1}
    torch.testing.assert_close(inverse_edges, forward_edges, rtol=0, atol=1e-4)
    torch.testing.assert_close(inverse_nodes, forward_nodes, rtol=0, atol=1e-4)
    torch.testing.assert_close(back.position, state.position, rtol=0, atol=1e-6)
    assert torch.equal(back.velocity_history[:, 1:], state.velocity_history[:, 1:])
    # the velocities are read: another v^t gives other conditions and another next velocity
    edge_index = radius_graph(state.position, model.radius)
    moved = state.velocity_history.clone()
    moved[:, -1] += 1e-3 * torch.randn_like(moved[:, -1])
    assert not torch.equal(model.conditions(state.position, state.particle_type, edge_index, moved[:, -1])[0],
                           forward_edges)
    with pytest.raises(ValueError, match="history >= 2"):
        RGNS(gravity_metadata(dim), history=1, latent=16, layers=2, edge_velocity=True)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("known_gravity", [False, True])
def test_unmasked_history_round_trip_is_exact_up_to_the_ilp_projection(dim, seed, known_gravity):
    """inverse_history(forward_history(V)) differs from V only because decoding then encoding
    projects the latent onto the range of W; the latent round trip itself is exact (with
    known_gravity too: the shift by g is undone before encoding)."""
    torch.manual_seed(seed)
    model = RGNS(gravity_metadata(dim), latent=16, layers=10, known_gravity=known_gravity)
    state = random_state(dim=dim, seed=seed)
    edge_index = radius_graph(state.position, model.radius)
    graph = (state.position, state.particle_type, edge_index)
    with torch.no_grad():
        identity = model.inverse_history(state.position, model.forward_history(state.position, state.velocity_history,
                                                                                state.particle_type, edge_index),
                                         state.particle_type, edge_index)
        scale = state.velocity_history.abs().max()
        torch.testing.assert_close(identity, state.velocity_history, rtol=0, atol=1e-6 * scale)  # at init

        perturb(model, seed=seed)
        edge_attr, condition = model.conditions(*graph)
        latent = model.encode(state.velocity_history)
        moved = model.processor(latent, edge_index, edge_attr, condition)
        torch.testing.assert_close(model.processor.inverse(moved, edge_index, edge_attr, condition), latent,
                                   rtol=0, atol=1e-5)
        projected = model.projection.encode(model.projection.decode(moved))
        expected = model.decode(model.processor.inverse(projected, edge_index, edge_attr, condition))
        forward = model.forward_history(state.position, state.velocity_history, state.particle_type, edge_index)
        round_trip = model.inverse_history(state.position, forward, state.particle_type, edge_index)
        torch.testing.assert_close(round_trip, expected, rtol=0, atol=1e-5 * scale)
        assert (moved - projected).abs().max() > 1e-2  # the projection is the whole gap, and it is not zero


@pytest.mark.parametrize("options", [dict(), dict(encoder="mlp"), dict(edges="updated"), dict(node_norm=False),
                                     dict(couplings="pairwise"), dict(couplings="pairwise", galilean=True)])
def test_rgns_memory_saving_gradients_equal_plain_gradients(options):
    torch.manual_seed(0)
    # float64: the memory-saving backward recomputes the inputs by inversion, which in float32
    # differs from the stored ones by round-off (~1e-7 of the gradient here): in float64 the two
    # gradients must agree to round-off
    model = RGNS(metadata(3), latent=16, layers=3, **options).double()
    perturb(model)
    batch = training_batch(dim=3)
    for key in ("pos", "forward_input", "forward_target", "inverse_input", "inverse_target"):
        batch[key] = batch[key].double()

    def gradients(memory_saving):
        model.processor.memory_saving = memory_saving
        model.zero_grad()
        graph = (batch.particle_type, batch.edge_index)
        if memory_saving:  # the training step's call: both directions sharing their conditions
            forward, inverse = model.both_velocities(batch.pos, batch.forward_input, batch.inverse_input, *graph)
        else:  # one direction at a time
            forward = model.next_velocity(batch.pos, batch.forward_input, *graph)
            inverse = model.oldest_velocity(batch.pos, batch.inverse_input, *graph)
        loss = (((forward - batch.forward_target) / model.acc_std_noisy) ** 2).mean() \
            + (((inverse - batch.inverse_target) / model.acc_std_noisy) ** 2).mean()
        loss.backward()
        return loss.detach(), [p.grad.clone() for p in model.parameters()]

    saving_loss, saving = gradients(True)
    plain_loss, plain = gradients(False)
    torch.testing.assert_close(saving_loss, plain_loss)
    for a, b in zip(saving, plain):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12 * b.abs().max().item())


# ---- sizes ------------------------------------------------------------------------------------

def test_parameter_counts_at_the_paper_sizes():
    gns, rgns, sep_gns = (count_parameters(cls(metadata())) for cls in (GNS, RGNS, SepGNS))
    assert abs(gns - 1.59e6) / 1.59e6 < 0.01  # DeepMind's GNS at latent 128, 10 layers
    assert abs(rgns - 0.78e6) / 0.78e6 < 0.05 and 0.45 < rgns / gns < 0.55  # paper: 0.78 M, half a GNS
    assert sep_gns == 2 * gns
    model = RGNS(metadata())
    assert len(model.processor.blocks) == 10 and model.projection.weight.shape == (128, 10)


def test_every_size_is_a_constructor_argument():
    small = RGNS(metadata(), history=3, latent=24, layers=4, hidden=8, hidden_layers=1)
    assert small.history == 3 and len(small.processor.blocks) == 4 and small.projection.weight.shape == (24, 6)
    assert count_parameters(GNS(metadata(), latent=32, layers=3)) < count_parameters(GNS(metadata(), latent=32))


def test_sep_gns_backward_network_runs_on_reversed_time():
    """With a zero acceleration the backward GNS extrapolates the oldest velocity at constant velocity."""
    model = SepGNS(metadata(), **SMALL)
    with torch.no_grad():
        model.backward_gns.decoder[-1].weight.zero_()
        model.backward_gns.decoder[-1].bias.zero_()
    state = random_state()
    edge_index = radius_graph(state.position, model.radius)
    oldest = model.oldest_velocity(state.position, state.velocity_history, state.particle_type, edge_index)
    torch.testing.assert_close(oldest, state.velocity_history[:, 0], rtol=0, atol=1e-8)
    assert model.backward_gns.vel_mean.neg().equal(model.forward_gns.vel_mean)


# ---- rollouts ---------------------------------------------------------------------------------

def test_state_from_positions():
    positions = torch.rand(K + 1, 10, 2)
    state = State.from_positions(positions, torch.full((10,), WATER))
    assert torch.equal(state.position, positions[-1])
    assert state.velocity_history.shape == (10, K, 2)
    torch.testing.assert_close(state.velocity_history[:, -1], positions[-1] - positions[-2])


@pytest.mark.parametrize("cls", [GNS, RGNS, SepGNS])
def test_rollouts_move_kinematic_particles_only_as_told(cls):
    torch.manual_seed(0)
    model = cls(metadata(), **SMALL)
    perturb(model)
    state = random_state(graphs=2)
    before = state.velocity_history.clone()
    kinematic = state.particle_type == KINEMATIC
    steps = 8
    still = model.rollout(state, steps)
    assert still.shape == (steps, *state.position.shape)
    assert torch.equal(still[:, kinematic], state.position[kinematic].expand(steps, -1, -1))
    assert not torch.equal(still[:, ~kinematic], state.position[~kinematic].expand(steps, -1, -1))
    moving = state.position + 1e-3 * torch.arange(1, steps + 1).view(-1, 1, 1)  # [steps, N, D]
    torch.testing.assert_close(model.rollout(state, steps, moving)[:, kinematic], moving[:, kinematic])
    assert torch.equal(state.velocity_history, before)  # the state is not consumed
    if not model.bidirectional:
        return
    back = model.inverse_rollout(state, steps)
    assert back.shape == (steps, *state.position.shape)
    torch.testing.assert_close(back[:, kinematic], state.position[kinematic].expand(steps, -1, -1))
    earlier = state.position - 1e-3 * torch.arange(1, steps + 1).view(-1, 1, 1)  # frames t-1 .. t-steps
    state.velocity_history[kinematic] = 1e-3  # consistent with the earlier kinematic frames
    back = model.inverse_rollout(state, steps, earlier)
    torch.testing.assert_close(back[:, kinematic], earlier[:, kinematic], rtol=0, atol=1e-6)


def test_inverse_rollout_undoes_a_forward_rollout_at_constant_velocity():
    model = RGNS(metadata())  # untrained: the identity latent map, exactly reversible physics
    state = random_state(particles=60)
    ahead = model.rollout(state, 6)
    last = State.from_positions(ahead[-K - 1:], state.particle_type)
    back = model.inverse_rollout(last, 6)  # frames t+5, .., t+1, t
    torch.testing.assert_close(back[:5], ahead[:5].flip(0), rtol=0, atol=1e-6)
    torch.testing.assert_close(back[5], state.position, rtol=0, atol=1e-6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_models_run_on_cuda():
    for cls in (GNS, RGNS, SepGNS):
        model = cls(metadata(), **SMALL).cuda()
        state = random_state().to("cuda")
        assert model.rollout(state, 2).device.type == "cuda"
        if model.bidirectional:
            assert model.inverse_rollout(state, 2).device.type == "cuda"


class _Collapsing(GNS):
    """Every particle jumps to the box's centre: a clump whose radius graph is complete."""

    def next_velocity(self, position, velocity_history, particle_type, edge_index, batch=None):
        return self.bounds.mean(dim=1) - position


def test_a_collapsed_rollout_stops_and_repeats_its_last_frame(caplog):
    state = random_state(dim=2, seed=3)
    model = _Collapsing(metadata(2), latent=8, layers=1)
    model.collapse_factor = 8.0  # the clump (72 water particles) against this random state's densest cell (under 9)
    with caplog.at_level("WARNING"):
        positions = model.rollout(state, 6)
    assert positions.shape == (6, *state.position.shape)
    assert "collapsed at step 1 of 6" in caplog.text
    assert torch.equal(positions[1:], positions[:1].expand(5, -1, -1))
    # a rollout that does not collapse is the same with and without the guard
    gns, unguarded = GNS(metadata(2), **SMALL), GNS(metadata(2), **SMALL)
    unguarded.load_state_dict(gns.state_dict())
    unguarded.collapse_factor = None
    torch.testing.assert_close(gns.rollout(state, 6), unguarded.rollout(state, 6), rtol=0, atol=0)
    assert model.densest_cell(positions[-1]) == int((state.particle_type != KINEMATIC).sum())  # the clump
    assert GNS.collapse_factor == 30.0  # the default, far past a fluid's compression or a pile at a wall


# ---- compiled networks (module.compile) ------------------------------------------------------

@pytest.mark.parametrize("cls, options", [(GNS, {}), (RGNS, {}), (GNS, {"decoder": "pairwise"}),
                                          (GNS, {"decoder": "pairwise", "galilean": True}),
                                          (RGNS, {"couplings": "pairwise"}),
                                          (RGNS, {"couplings": "pairwise", "galilean": True})])
def test_compiled_network_computes_what_the_eager_one_does(cls, options):
    """compile_network changes how the network runs, not what it computes: the same velocities
    and gradients on two batches of different sizes (dynamic shapes), and a copy runs eager."""
    import copy

    torch.manual_seed(0)
    data = gravity_metadata(2) if options else metadata()  # the pair terms' reference is gravity
    eager = cls(data, history=K, latent=16, layers=1, **options, **({"memory_saving": False} if cls is RGNS else {}))
    perturb(eager)
    compiled = copy.deepcopy(eager)
    compiled.compile_network(dynamic=True)
    assert compiled.compiled and not eager.compiled
    for graphs, seed in ((2, 0), (3, 1)):
        batch = training_batch(graphs=graphs, seed=seed)
        args = (batch.pos, batch.forward_input, batch.particle_type, batch.edge_index, batch.batch)
        outputs = {}
        for name, model in (("eager", eager), ("compiled", compiled)):
            model.zero_grad()
            if model.bidirectional:
                velocities = model.both_velocities(batch.pos, batch.forward_input, batch.inverse_input,
                                                   batch.particle_type, batch.edge_index, batch.batch)
            else:
                velocities = (model.next_velocity(*args),)
            sum(v.pow(2).sum() for v in velocities).backward()
            outputs[name] = (velocities, [p.grad.clone() for p in model.parameters()])
        for got, want in zip(outputs["compiled"][0], outputs["eager"][0]):
            torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-7)
        for got, want in zip(outputs["compiled"][1], outputs["eager"][1]):
            torch.testing.assert_close(got, want, rtol=1e-3, atol=1e-7)
    assert list(compiled.state_dict()) == list(eager.state_dict())  # checkpoints are alike
    copied = copy.deepcopy(compiled)  # e.g. the EMA's averaged model: eager, the same function
    assert not copied.compiled
    torch.testing.assert_close(copied.next_velocity(*args), eager.next_velocity(*args))


def test_rgns_refuses_to_compile_its_memory_saving_backward():
    model = RGNS(metadata(), history=K, latent=16, layers=1, memory_saving=True)
    with pytest.raises(ValueError, match="memory_saving=false"):
        model.compile_network(dynamic=True)
    assert not model.compiled


def turns_nan(after: int = 3) -> tuple[torch.nn.Module, State]:
    """Constant velocity whose predicted velocity turns NaN from its ``after + 1``-th call, and a
    6 x 6 lattice of water with a 3-velocity history."""
    from rgns.evaluation.baselines import ConstantVelocity

    class TurnsNaN(ConstantVelocity):
        calls = 0

        def next_velocity(self, *args, **kwargs):
            return self.planted(super().next_velocity(*args, **kwargs))

        def oldest_velocity(self, *args, **kwargs):
            return self.planted(super().oldest_velocity(*args, **kwargs))

        def planted(self, velocity):
            self.calls += 1
            return velocity if self.calls <= after else torch.full_like(velocity, float("nan"))

    metadata = dict(bounds=[[0.0, 1.0]] * 2, default_connectivity_radius=0.1, dim=2, dt=0.0025, sequence_length=20,
                    vel_mean=[0.0] * 2, vel_std=[1e-3] * 2, acc_mean=[0.0] * 2, acc_std=[1e-4] * 2)
    axis = torch.linspace(0.3, 0.7, 6)
    position = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    return TurnsNaN(metadata, history=3), State(position, torch.full((36, 3, 2), 1e-3), torch.full((36,), WATER))


@pytest.mark.parametrize("backwards", [False, True])
def test_a_rollout_that_turns_non_finite_is_nan_from_there_not_a_crash(backwards):
    """A model whose velocity turns NaN at its 4th step: the frames it reaches are NaN and the
    rollout ends with NaN frames where building a radius graph of NaN positions used to raise."""
    model, state = turns_nan()
    frames = model.inverse_rollout(state, 12) if backwards else model.rollout(state, 12)
    finite = torch.isfinite(frames).flatten(1).all(1)
    # forward: the 4th step's frame is NaN, and the 5th step's graph would be built on it; backward: the
    # NaN velocity enters the history as its oldest and reaches the newest, which the next graph's
    # positions p - v subtract, 2 steps later, so the 6th step is the last and frame 7 the first NaN one
    first_nan, last_call = (6, 6) if backwards else (3, 4)
    assert finite[:first_nan].all() and not finite[first_nan:].any()
    assert model.calls == last_call  # no step after the one whose next graph would be NaN


def test_an_inverse_that_turns_non_finite_gets_a_nan_resimulation_not_a_crash():
    """The inverse task's inverse-then-forward: NaN from where the inverse broke, and no forward run
    from a state that holds NaN (its first graph would raise)."""
    from rgns.training.rollouts import inverse_then_forward

    model, state = turns_nan()
    truth = torch.stack([state.position + 1e-3 * t for t in range(20)])  # [20, N, D]: the lattice drifting
    inferred, resimulated = inverse_then_forward(model, truth, state.particle_type, start=4, steps=12)
    assert inferred.shape == resimulated.shape == (12, 36, 2)
    assert torch.isfinite(inferred[:6]).all() and torch.isnan(inferred[6:]).all()
    assert torch.isnan(resimulated).all() and model.calls == 6
    model, _ = turns_nan(after=10**6)  # never planted: exact both ways on the drifting lattice
    inferred, resimulated = inverse_then_forward(model, truth, state.particle_type, start=4, steps=12)
    assert torch.allclose(inferred, truth[4:16].flip(0), atol=1e-6)
    assert torch.allclose(resimulated, truth[5:17], atol=1e-6)
