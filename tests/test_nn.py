"""Unit tests of the PyG layers: exactness of the ILP and of RRMP, memory saving, messages."""
from __future__ import annotations

import pytest
import torch

from rgns.data.graph import radius_graph
from rgns.nn import ILP, RRMP, Coupling, InteractionNetwork

torch.set_num_threads(1)


def random_graph(nodes: int, dim: int, seed: int, neighbours: float = 8.0):
    """Uniform points in the unit box and their radius graph with about ``neighbours`` per node."""
    generator = torch.Generator().manual_seed(seed)
    position = torch.rand(nodes, dim, generator=generator)
    ball = {2: torch.pi, 3: 4 / 3 * torch.pi}[dim]
    radius = (neighbours / (nodes * ball)) ** (1 / dim)
    return position, radius_graph(position, radius), generator


def perturb(module: torch.nn.Module, scale: float, generator: torch.Generator) -> None:
    """Move every parameter off its initialisation (the zero-initialised couplings included)."""
    with torch.no_grad():
        for parameter in module.parameters():
            parameter.add_(scale * torch.randn(parameter.shape, generator=generator))


@pytest.mark.parametrize("in_channels,out_channels", [(10, 128), (15, 64), (30, 128), (6, 16)])
def test_ilp_decode_inverts_encode(in_channels, out_channels):
    generator = torch.Generator().manual_seed(in_channels * out_channels)
    ilp = ILP(in_channels, out_channels)
    with torch.no_grad():  # a learned W is not orthogonal: test a generic one
        ilp.weight.copy_(torch.randn(out_channels, in_channels, generator=generator) / in_channels**0.5)
        ilp.bias.copy_(torch.randn(out_channels, generator=generator))
    x = torch.randn(500, in_channels, generator=generator)
    n = ilp.encode(x)
    assert n.shape == (500, out_channels)
    torch.testing.assert_close(ilp.decode(n), x, rtol=0, atol=1e-6)


def test_ilp_encode_decode_is_a_projection():
    torch.manual_seed(0)
    ilp = ILP(10, 32)
    n = torch.randn(100, 32)
    projected = ilp.encode(ilp.decode(n))
    assert (projected - n).abs().max() > 0.1  # a latent off the range is not recovered ...
    torch.testing.assert_close(ilp.encode(ilp.decode(projected)), projected, rtol=0, atol=1e-5)  # ... its projection is


def test_ilp_refuses_a_narrower_latent():
    with pytest.raises(ValueError, match="invertible"):
        ILP(10, 8)


def make_rrmp(channels, layers, condition_channels, edges, seed):
    torch.manual_seed(seed)
    rrmp = RRMP(channels, layers, condition_channels, edges=edges)
    return rrmp


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("channels,nodes,edges", [(16, 200, "fixed"), (32, 80, "fixed"), (16, 120, "updated")])
def test_rrmp_inverse_recovers_latent_at_ten_layers(dim, channels, nodes, edges):
    position, edge_index, generator = random_graph(nodes, dim, seed=channels + nodes + dim)
    rrmp = make_rrmp(channels, 10, 20, edges, seed=dim)
    perturb(rrmp, 0.1, generator)
    x = torch.randn(nodes, channels, generator=generator)
    edge_attr = torch.randn(edge_index.size(1), channels, generator=generator)
    condition = torch.randn(nodes, 20, generator=generator)
    with torch.no_grad():
        y = rrmp(x, edge_index, edge_attr, condition)
        assert (y - x).abs().max() > 0.1  # the map is far from the identity
        torch.testing.assert_close(rrmp.inverse(y, edge_index, edge_attr, condition), x, rtol=0, atol=1e-5)
        torch.testing.assert_close(rrmp(rrmp.inverse(x, edge_index, edge_attr, condition), edge_index, edge_attr,
                                        condition), x, rtol=0, atol=1e-5)


@pytest.mark.parametrize("node_norm", [True, False])
def test_rrmp_starts_as_the_identity(node_norm):
    position, edge_index, generator = random_graph(50, 2, seed=1)
    rrmp = RRMP(16, 3, 20, node_norm=node_norm)
    x = torch.randn(50, 16, generator=generator)
    with torch.no_grad():
        y = rrmp(x, edge_index, torch.randn(edge_index.size(1), 16), torch.randn(50, 20))
    assert torch.equal(y, x)


@pytest.mark.parametrize("edges", ["fixed", "updated"])
def test_rrmp_memory_saving_gradients_equal_plain_gradients(edges):
    position, edge_index, generator = random_graph(100, 3, seed=7)
    rrmp = make_rrmp(16, 4, 20, edges, seed=3)
    perturb(rrmp, 0.1, generator)
    x = torch.randn(100, 16, generator=generator)
    edge_attr = torch.randn(edge_index.size(1), 16, generator=generator)
    condition = torch.randn(100, 20, generator=generator)
    target = torch.randn(100, 16, generator=generator)

    def gradients(memory_saving):
        rrmp.memory_saving = memory_saving
        rrmp.zero_grad()
        inputs = [t.clone().requires_grad_() for t in (x, edge_attr, condition)]
        latent = inputs[0] * 1.0  # RRMP frees the storage of what it is given
        forward = rrmp(latent, edge_index, *inputs[1:])
        freed = latent.untyped_storage().size() == 0
        backward = rrmp.inverse(inputs[0] * 1.0, edge_index, *inputs[1:])
        (((forward - target) ** 2).sum() + ((backward - target) ** 2).sum()).backward()
        return freed, [t.grad for t in inputs] + [p.grad.clone() for p in rrmp.parameters()]

    freed, saving = gradients(True)
    assert freed, "memory saving did not free the input"
    freed, plain = gradients(False)
    assert not freed
    assert len(saving) == len(plain) and all(g.abs().max() > 0 for g in plain)
    for a, b in zip(saving, plain):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_rrmp_refuses_conditions_as_wide_as_the_latent():
    with pytest.raises(ValueError, match="split"):
        RRMP(20, 2, 20)


def test_interaction_network_matches_a_dense_loop():
    torch.manual_seed(0)
    layer = InteractionNetwork(8)
    x, edge_index = torch.randn(6, 8), torch.tensor([[0, 1, 2, 3, 5, 5], [1, 0, 1, 1, 4, 0]])
    edge_attr = torch.randn(6, 8)
    x_new, edge_new = layer(x, edge_index, edge_attr)
    aggregated = torch.zeros(6, 8)
    for e, (j, i) in enumerate(edge_index.t().tolist()):
        message = layer.edge_mlp(torch.cat([edge_attr[e], x[i], x[j]]))
        torch.testing.assert_close(edge_new[e], edge_attr[e] + message)
        aggregated[i] += message
    torch.testing.assert_close(x_new, x + layer.node_mlp(torch.cat([x, aggregated], dim=-1)))


def test_coupling_reads_neighbours_and_conditions():
    torch.manual_seed(0)
    f = Coupling(8, 5, zero_init=False)
    x, condition = torch.randn(4, 8), torch.randn(4, 5)
    edge_index = torch.tensor([[0], [1]])  # 0 -> 1; nodes 2 and 3 alone
    edge_attr = torch.randn(1, 8)
    out = f(x, edge_index, edge_attr, condition)  # its first layer split equals the concatenation
    assert out.shape == (4, 8)
    alone = f.node_mlp(torch.cat([x[2:], condition[2:], torch.zeros(2, 8)], dim=-1))
    torch.testing.assert_close(out[2:], alone)
    message = f.edge_mlp(torch.cat([edge_attr[0], x[1], x[0]]))
    torch.testing.assert_close(out[1], f.node_mlp(torch.cat([x[1], condition[1], message])))


def test_memory_saving_evaluates_each_coupling_twice_per_training_pass():
    """Forward without gradients, then one evaluation with gradients in the backward pass that both
    rebuilds the input and differentiates (GroupAddRev's own backward evaluates a third time)."""
    position, edge_index, generator = random_graph(60, 2, seed=11)
    rrmp = make_rrmp(16, 3, 20, "fixed", seed=5)
    perturb(rrmp, 0.1, generator)
    calls = []
    for block in rrmp.blocks:
        for conv in block.convs:
            conv.register_forward_hook(lambda module, args, out: calls.append(module))
    couplings = [conv for block in rrmp.blocks for conv in block.convs]
    edge_attr = torch.randn(edge_index.size(1), 16, generator=generator)
    condition = torch.randn(60, 20, generator=generator)
    for direction in (rrmp.forward, rrmp.inverse):
        calls.clear()
        x = torch.randn(60, 16, generator=generator, requires_grad=True)
        direction(x * 1.0, edge_index, edge_attr, condition).pow(2).sum().backward()
        assert x.grad is not None and x.grad.abs().max() > 0
        assert all(sum(c is conv for c in calls) == 2 for conv in couplings), [sum(c is conv for c in calls) for conv in couplings]


def test_coupling_increment_is_bounded_by_its_layer_norm():
    """With ``node_norm`` no input, however far from the training data, makes a coupling add
    more than its LayerNorm allows (|gain| sqrt(H) + |bias| per node); without it the
    increment grows with the input."""
    torch.manual_seed(0)
    position, edge_index, generator = random_graph(60, 2, seed=4)
    x, condition = torch.randn(60, 8, generator=generator), torch.randn(60, 5, generator=generator)
    edge_attr = torch.randn(edge_index.size(1), 8, generator=generator)
    normed, plain = Coupling(8, 5, zero_init=False), Coupling(8, 5, zero_init=False, node_norm=False)
    norm = normed.node_mlp[-1]
    with torch.no_grad():
        norm.weight.normal_(generator=generator)
        norm.bias.normal_(generator=generator)
        bound = norm.weight.abs().max() * 8**0.5 + norm.bias.norm()
        for scale in (1.0, 1e3, 1e6):
            assert normed(scale * x, edge_index, edge_attr, condition).norm(dim=-1).max() <= bound * (1 + 1e-5)
        small, large = (plain(scale * x, edge_index, edge_attr, condition).norm(dim=-1).max() for scale in (1.0, 1e3))
    assert large > 100 * small
