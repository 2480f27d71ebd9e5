"""The forward rollout step, before and after: ``python -m rgns.bench step [--checkpoints ...] [--steps N]``.

Times, on one thread, the rollout step of each checkpoint (by default the shipped
``pretrained/waterdrop40_main_64`` R-GNS and GNS) on a test trajectory of its dataset three ways,
in turns on the same states (one of each per round, the order rotated; median over the rounds):

- ``old``: :func:`reference_step`, the step as it was before the work of docs/benchmarks.md's
  "forward rollout step" section: a fresh radius graph every step, the pair terms antisymmetrised
  through each edge's reverse (found by a sort), the ILP's pseudo-inverse (an SVD) and the rest
  frame's projection (a solve per coupling) computed in every step, the edge MLPs' first layer as
  a separate product and two sums;
- ``new``: :meth:`~rgns.models.base.Simulator.step` with the rollout's neighbour list;
- ``bf16``: the same with ``precision="bfloat16"`` (an option, not the default).

Each timed call advances ``--steps`` steps from the same state. It prints the ms per step and
the ratio old / new, how far the new step's positions are from the old one's (one step, and a
rollout of ``--steps``), a roofline line (the step's FLOPs, ``FlopCounterMode``, over its time,
against a 1024-square fp32 ``torch.mm`` timed on the same thread in the same rounds), and the
radius graph's cost per step over the true frames, fresh and from neighbour lists. ``--compile`` also
times a compiled rollout (``Simulator.compile_network``) of ``--compile-steps`` steps, compilation
included, against the eager one. ``--shapes STEPS`` times a rollout of STEPS steps in float32 and
in bfloat16 twice each, the second pass on the same graphs as the first: a rollout meets a new
edge count (a new shape of every edge product) at almost every step, and the second pass shows
what a step costs once each shape has been met.
"""
from __future__ import annotations

import argparse
import copy
import time

import torch
from torch import Tensor
from torch.nn import functional as F
from torch.utils.flop_counter import FlopCounterMode

from rgns.bench.models import interleaved_median_ms, keep_freed_memory
from rgns.data.contract import KINEMATIC, open_split
from rgns.data.graph import (NeighbourList, batched_radius_graph, radius_graph, reverse_edges, wall_distance,
                             wall_gate)
from rgns.models import GNS, RGNS, State
from rgns.models.base import Simulator
from rgns.nn.mlp import edge_input_terms

PEAK_SIZE = 1024  # the square torch.mm whose rate stands for the machine's fp32 peak
CHECKPOINTS = ["pretrained/waterdrop40_main_64/rgns.ckpt", "pretrained/waterdrop40_main_64/gns.ckpt"]


# ---- the old step, kept as the reference the new one is timed and tested against ---------------

def reference_step(model: Simulator, state: State) -> State:
    """One forward step computed as before the speed-ups (see the module docstring): the same
    function of the state as :meth:`~rgns.models.base.Simulator.step`, up to float32 rounding.
    R-GNS with the ILP encoder and GNS; float32 only."""
    position, history = state.position, state.velocity_history
    edge_index = batched_radius_graph(position, model.radius, state.batch)  # a fresh graph
    velocity = reference_next_velocity(model, position, history, state.particle_type, edge_index)
    if model.hard_walls:
        velocity = model.stop_at_walls(position, velocity)
    kinematic = (state.particle_type == KINEMATIC).unsqueeze(-1)
    velocity = torch.where(kinematic, torch.zeros_like(position), velocity)
    history = torch.cat([history[:, 1:], velocity.unsqueeze(1)], dim=1)
    return State(position + velocity, history, state.particle_type, state.batch)


def reference_next_velocity(model: Simulator, position: Tensor, history: Tensor, particle_type: Tensor,
                            edge_index: Tensor) -> Tensor:
    if isinstance(model, RGNS):
        return _rgns_next_velocity(model, position, history, particle_type, edge_index)
    if isinstance(model, GNS):
        return _gns_next_velocity(model, position, history, particle_type, edge_index)
    raise TypeError(f"no reference step for {type(model).__name__}")


def _rgns_next_velocity(model: RGNS, position, history, particle_type, edge_index) -> Tensor:
    edge_attr, condition = model.conditions(position, particle_type, edge_index, history[:, -1])
    latent = model.projection.encode(model.to_basis(history).flatten(1))  # [N, C]
    frame = model._boost_frame() if model.galilean else None  # computed every step
    reverse = reverse_edges(edge_index, len(position)) if model.processor.pairwise else None
    for block, edge_latent in zip(model.processor.blocks, model.processor.edge_latents(edge_attr)):
        first, second = latent.chunk(2, dim=-1)
        f_edges, g_edges = edge_latent.chunk(2, dim=-1)
        # f reads the second half of the latent, so the frame's second half, and g the first
        f_frame, g_frame = (None, None) if frame is None else frame.chunk(2, dim=-1)[::-1]
        first = first + _coupling(block.convs[0], second, edge_index, f_edges, condition, reverse, f_frame)
        second = second + _coupling(block.convs[1], first, edge_index, g_edges, condition, reverse, g_frame)
        latent = torch.cat([first, second], dim=-1)
    ilp = model.projection
    pseudo_inverse = torch.linalg.pinv(ilp.weight.double())  # an SVD every step
    decoded = F.linear(latent.double() - ilp.bias.double(), pseudo_inverse).to(latent.dtype)
    return (model.from_basis(decoded.unflatten(1, (model.history, model.dim))) + model.gravity_shift)[:, -1]


def _coupling(coupling, x, edge_index, edge_attr, condition, reverse, frame) -> Tensor:
    sender, receiver = edge_index
    edge_term, receiver_term, sender_term = edge_input_terms(coupling.edge_mlp, coupling.channels, x, edge_attr)
    if frame is not None:
        weight = coupling.edge_mlp[0].weight[:, coupling.channels :]
        own, other = weight.chunk(2, dim=1)
        directions, origin = frame[:-1], frame[-1]
        projection = directions.T @ torch.linalg.solve(directions @ directions.T, directions)  # every step
        receiver_term = receiver_term - F.linear(x - origin, (own + other) @ projection)
    message = coupling.edge_mlp[1:]((edge_term + receiver_term[receiver]).add_(sender_term[sender]))
    if coupling.pairwise:
        message = message - message[reverse]  # m_ij - m_ji
    aggregated = torch.zeros_like(x).index_add_(0, receiver, message)
    if coupling.pairwise:
        near = wall_gate(condition[:, : coupling.wall_channels])
        return aggregated + near * coupling.node_mlp(torch.cat([x, condition], dim=-1))
    return coupling.node_mlp(torch.cat([x, condition, aggregated], dim=-1))


def _gns_next_velocity(model: GNS, position, history, particle_type, edge_index) -> Tensor:
    geometry = model.geometry(position, history, edge_index)
    x, edge_attr = model.encode(position, history, particle_type, geometry)
    sender, receiver = edge_index
    for layer in model.processor:
        edge_term, receiver_term, sender_term = edge_input_terms(layer.edge_mlp, layer.channels, x, edge_attr)
        message = layer.edge_mlp[1:]((edge_term + receiver_term[receiver]).add_(sender_term[sender]))
        aggregated = torch.zeros_like(x).index_add_(0, receiver, message)
        x, edge_attr = x + layer.node_mlp(torch.cat([x, aggregated], dim=-1)), edge_attr + message
    reference = model.gravity_reference if model.known_gravity else model.acc_mean
    if not model.pairwise:
        return history[:, -1] + model.decoder(x) * model.acc_std_noisy + reference
    into = model.decoder(torch.cat([x[receiver], x[sender], geometry], -1))  # psi(h_i, h_j, g_ij)
    back = into[reverse_edges(edge_index, len(x))]  # psi on the reverse edge
    pairs = torch.zeros_like(position).index_add_(0, receiver, into - back)
    walls = wall_distance(position, model.bounds, model.radius)
    wall_in = torch.cat([x, model.normalise_velocity(history[:, -1])], -1) if model.galilean else x
    acceleration = (pairs + wall_gate(walls) * model.wall_decoder(wall_in)) * model.acc_std_noisy + reference
    return history[:, -1] + acceleration


# ---- measuring -----------------------------------------------------------------------------

def rollout_positions(step, state: State, steps: int) -> Tensor:
    """``step(state) -> state`` applied ``steps`` times.  ``[steps, N, D]``"""
    positions = []
    for _ in range(steps):
        state = step(state)
        positions.append(state.position)
    return torch.stack(positions)


def new_stepper(model: Simulator):
    """The rollout's step: :meth:`Simulator.step` with one neighbour list kept between calls."""
    neighbours = NeighbourList(model.radius, model.neighbour_skin * model.radius)
    return lambda state: model.step(state, None, neighbours)


@torch.no_grad()
def one_step_along(model: Simulator, state: State, steps: int) -> float:
    """The largest difference of the new and the old step's positions from each state of a new
    rollout of ``steps`` steps (the same function, state by state, however far the rollouts part)."""
    step, worst = new_stepper(model), 0.0
    for _ in range(steps):
        new = step(state)
        worst = max(worst, float((new.position - reference_step(model, state).position).abs().max()))
        state = new
    return worst


def first_graph_change(model: Simulator, runs: dict[str, Tensor]) -> int | None:
    """The first step after which the old and the new rollout's radius graphs differ (``None``: never)."""
    for index, (old, new) in enumerate(zip(runs["old"], runs["new"])):
        edges = [set(map(tuple, radius_graph(p, model.radius).t().tolist())) for p in (old, new)]
        if edges[0] != edges[1]:
            return index + 1
    return None


def step_flops(step, state: State) -> int:
    """The FLOPs of one call of ``step`` (matrix products; the in-place ``addmm_`` counted too)."""
    def addmm_flops(self_shape, mat1_shape, mat2_shape, *args, **kwargs) -> int:
        return 2 * mat1_shape[0] * mat1_shape[1] * mat2_shape[1]

    counter = FlopCounterMode(display=False, custom_mapping={torch.ops.aten.addmm_: addmm_flops})
    with counter:
        step(state)
    return counter.get_total_flops()


def matmul_peak_gflops(dtype: torch.dtype = torch.float32, size: int = 2048, repeats: int = 5) -> float:
    """GFLOP/s of a ``size``-square ``torch.mm`` on this thread (the best of ``repeats``)."""
    a, b = torch.randn(size, size).to(dtype), torch.randn(size, size).to(dtype)
    torch.mm(a, b)
    best = min(_seconds(lambda: torch.mm(a, b)) for _ in range(repeats))
    return 2 * size**3 / best / 1e9


def _seconds(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def start_state(dataset: str, trajectory: int, frame: int, history: int) -> State:
    """The state at ``frame`` of a test trajectory (its ``history`` velocities from the frames before)."""
    with open_split(dataset, "test") as split:
        data = split[trajectory]
        position, particle_type = torch.as_tensor(data.position), torch.as_tensor(data.particle_type)
    return State.from_positions(position[frame - history : frame + 1], particle_type)


def measure(path: str, args) -> None:
    from rgns.training.module import load_simulator  # the training layer, for checkpoints only

    model, _ = load_simulator(path)
    state = start_state(args.dataset, args.trajectory, args.frame, model.history)
    box = float((model.bounds[:, 1] - model.bounds[:, 0]).max())
    low = copy.deepcopy(model)
    low.precision = "bfloat16"
    with torch.no_grad():
        steppers = {"old": lambda s: reference_step(model, s), "new": new_stepper(model), "bf16": new_stepper(low)}
        one = {name: step(state).position for name, step in steppers.items()}
        runs = {name: rollout_positions(step, state, args.steps) for name, step in steppers.items()}
        timed = {name: (lambda step=step: rollout_positions(step, state, args.steps)) for name, step in steppers.items()}
        a, b = torch.randn(PEAK_SIZE, PEAK_SIZE), torch.randn(PEAK_SIZE, PEAK_SIZE)
        timed["mm"] = lambda: torch.mm(a, b)  # the roofline's peak, timed in the same rounds
        times = interleaved_median_ms(timed, args.rounds, torch.device("cpu"))
        flops = step_flops(steppers["new"], state)
    edges = batched_radius_graph(state.position, model.radius).size(1)
    peak = 2 * PEAK_SIZE**3 / (times.pop("mm") * 1e6)  # GFLOP/s
    per_step = {name: ms / args.steps for name, ms in times.items()}
    print(f"{path}: {type(model).__name__} {len(state.position)} particles, {edges} edges, {args.steps} steps "
          f"from frame {args.frame} of test trajectory {args.trajectory}, median of {args.rounds} rounds")
    print(f"  old {per_step['old']:7.2f} ms/step   new {per_step['new']:7.2f} ms/step   "
          f"old/new {per_step['old'] / per_step['new']:.2f}x")
    print(f"  bf16 {per_step['bf16']:6.2f} ms/step   old/bf16 {per_step['old'] / per_step['bf16']:.2f}x   "
          f"new/bf16 {per_step['new'] / per_step['bf16']:.2f}x")
    for name in ("new", "bf16"):
        first = float((one[name] - one["old"]).abs().max()) / box
        rollout = float((runs[name] - runs["old"]).abs().max()) / box
        print(f"  {name} - old, max |position| / box side: after 1 step {first:.1e}, "
              f"over {args.steps} steps {rollout:.1e}")
    along = one_step_along(model, state, args.steps) / box
    print(f"  new - old from each state of the new rollout, one step: at most {along:.1e} of the box side; "
          f"the two rollouts' radius graphs first differ after step {first_graph_change(model, runs)}")
    achieved = flops / (per_step["new"] * 1e6)
    print(f"  roofline: {flops / 1e9:.3f} GFLOP per step (matrix products), new {achieved:.1f} GFLOP/s, "
          f"old {flops / (per_step['old'] * 1e6):.1f} GFLOP/s, against {peak:.1f} GFLOP/s of a fp32 "
          f"torch.mm {PEAK_SIZE}^2 in the same rounds ({100 * achieved / peak:.0f}% of it)")
    neighbour_lists(args, model.radius)
    if args.compile:
        compiled_rollout(model, state, args.compile_steps)
    if args.shapes:
        new_shapes(model, low, state, args.shapes)
    if args.mse:
        precision_mse(model, low, args)


def new_shapes(model: Simulator, low: Simulator, state: State, steps: int) -> None:
    """A rollout of ``steps`` steps in float32 and in bfloat16, each run twice in a row (the second
    pass meets the same edge counts as the first): ms per step of each pass, and the edge counts met."""
    line, counts = [], set()  # counts: the float32 rollout's
    with torch.no_grad():
        for name, simulator in (("fp32", model), ("bf16", low)):
            passes = []
            for _ in range(2):
                start = time.perf_counter()
                positions = rollout_positions(new_stepper(simulator), state, steps)
                passes.append(1e3 * (time.perf_counter() - start) / steps)
            if name == "fp32":
                counts = {batched_radius_graph(p, model.radius).size(1) for p in positions}
            line.append(f"{name} {passes[0]:.2f} then {passes[1]:.2f} ms/step")
    print(f"  a rollout of {steps} steps, twice ({len(counts)} distinct edge counts in its graphs): " + "; ".join(line))


def precision_mse(model: Simulator, low: Simulator, args) -> None:
    """Rollout MSE (1e-3, all particles, as the evaluation's) over the first ``args.mse`` test
    trajectories, ``args.mse_steps`` steps from ``args.frame``: the old step, the new one in
    float32 and in bfloat16."""
    errors = {"old": [], "new": [], "bf16": []}
    with open_split(args.dataset, "test") as split, torch.no_grad():
        for index in range(min(args.mse, len(split))):
            data = split[index]
            position, particle_type = torch.as_tensor(data.position), torch.as_tensor(data.particle_type)
            if bool((particle_type == KINEMATIC).any()):
                raise ValueError("--mse compares free rollouts: this dataset has kinematic particles")
            truth = position[args.frame + 1 : args.frame + 1 + args.mse_steps]
            state = State.from_positions(position[args.frame - model.history : args.frame + 1], particle_type)
            steppers = {"old": lambda s: reference_step(model, s),  # the new ones with a fresh neighbour list each
                        "new": new_stepper(model), "bf16": new_stepper(low)}
            for name, step in steppers.items():
                errors[name].append(1e3 * float((rollout_positions(step, state, len(truth)) - truth).pow(2).mean()))
    line = ", ".join(f"{name} {sum(e) / len(e):.4f}" for name, e in errors.items())
    print(f"  rollout MSE (1e-3) over {len(errors['old'])} test trajectories, {args.mse_steps} steps from frame "
          f"{args.frame}: {line}")
    for name, e in errors.items():
        print(f"    {name:5s} " + " ".join(f"{x:.4f}" for x in e))


def neighbour_lists(args, radius: float) -> None:
    """The radius graphs of the true trajectory's next ``args.compile_steps`` frames, one after the
    other: fresh, and from neighbour lists with skins of ``args.skins`` times R (a new list per pass)."""
    with open_split(args.dataset, "test") as split:
        frames = torch.as_tensor(split[args.trajectory].position)[args.frame : args.frame + args.compile_steps + 1]
    skins = {"fresh": 0.0} | {f"skin {skin:g} R": skin * radius for skin in args.skins}

    def run(skin: float) -> NeighbourList:
        neighbours = NeighbourList(radius, skin)
        for position in frames:
            neighbours(position)
        return neighbours

    times = interleaved_median_ms({name: (lambda skin=skin: run(skin)) for name, skin in skins.items()}, 3,
                                  torch.device("cpu"))
    builds = {name: f" ({run(skin).builds} builds)" if skin else "" for name, skin in skins.items()}
    line = ", ".join(f"{name} {ms / len(frames):.2f} ms{builds[name]}" for name, ms in times.items())
    print(f"  radius graph per step over {len(frames)} true frames: {line}")


def compiled_rollout(model: Simulator, state: State, steps: int) -> None:
    """Eager and compiled rollouts of ``steps`` steps, the compiled one's time including its compilation."""
    compiled = copy.deepcopy(model)
    if isinstance(compiled, RGNS):
        compiled.processor.memory_saving = False  # no effect without gradients; compile_network asks for it
    compiled.compile_network(dynamic=True)
    eager_s = _seconds(lambda: model.rollout(state, steps))
    compiled_s = _seconds(lambda: compiled.rollout(state, steps))
    again_s = _seconds(lambda: compiled.rollout(state, steps))
    print(f"  compiled rollout of {steps} steps: eager {eager_s:.1f} s, compiled {compiled_s:.1f} s with its "
          f"compilation, {again_s:.1f} s compiled again: pays {'yes' if compiled_s < eager_s else 'no'} "
          f"(eager/compiled {eager_s / compiled_s:.2f}x, without compiling {eager_s / again_s:.2f}x)")


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(prog="python -m rgns.bench step", description=__doc__.split("\n")[0])
    parser.add_argument("--checkpoints", nargs="+", default=CHECKPOINTS)
    parser.add_argument("--dataset", default="datasets/waterdrop40_main", help="whose test trajectory is stepped")
    parser.add_argument("--trajectory", type=int, default=0)
    parser.add_argument("--frame", type=int, default=5, help="the start frame (its history before it)")
    parser.add_argument("--steps", type=int, default=10, help="steps per timed call")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--compile", action="store_true", help="also time a compiled rollout, compilation included")
    parser.add_argument("--compile-steps", type=int, default=300, help="also the frames of the neighbour-list line")
    parser.add_argument("--skins", type=float, nargs="*", default=[0.2, 0.5], help="neighbour-list skins (of R) timed")
    parser.add_argument("--shapes", type=int, default=0, metavar="STEPS",
                        help="also a rollout of STEPS steps twice in float32 and in bfloat16 (new shapes, then met ones)")
    parser.add_argument("--mse", type=int, default=0, metavar="TRAJECTORIES",
                        help="also the rollout MSE of old, new and bf16 over this many test trajectories")
    parser.add_argument("--mse-steps", type=int, default=300)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    keep_freed_memory()
    print(f"one thread; torch.mm 2048^2, best of 5: fp32 {matmul_peak_gflops():.1f} GFLOP/s, "
          f"bf16 {matmul_peak_gflops(torch.bfloat16):.1f} GFLOP/s")
    for path in args.checkpoints:
        measure(path, args)
