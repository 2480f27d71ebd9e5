"""Cost of the simulators at the paper's sizes: ``python -m rgns.bench models --json PATH``.

One process, one thread, one random 1,000-particle 2D scene (about 20 neighbours per particle)
shared by every model. Reports parameters, inference step (``step`` / ``inverse_step``, radius
graph included), training step (forward, loss, backward) and peak training memory. Peak memory
on the CPU is the rise of the resident set over one training step, each model measured in a
fresh subprocess with glibc's mmap threshold fixed at 64 KiB, so that freed tensors leave the
resident set at once (on CUDA, ``torch.cuda.max_memory_allocated``).

Training steps: GNS with its forward loss; R-GNS with the forward and the inverse loss on the
same batch (its real training step, memory-saving backward), plus R-GNS† (forward loss only),
R-GNS without memory saving, and Sep-GNS (both of its GNS, one loss each: the other way to
train both directions) for reference.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import multiprocessing
import statistics
import time
from pathlib import Path

import torch

from rgns.data.contract import WATER
from rgns.data.graph import radius_graph
from rgns.models import GNS, RGNS, SepGNS, State, count_parameters

# WaterDrop's statistics (DeepMind's metadata); the radius is set for ~20 neighbours.
METADATA = dict(bounds=[[0.1, 0.9], [0.1, 0.9]], dim=2, dt=0.0025, sequence_length=1000,
                vel_mean=[-3.96e-5, -2.63e-4], vel_std=[1.37e-3, 1.31e-3], acc_mean=[2.6e-8, 1.07e-7],
                acc_std=[6.74e-5, 8.70e-5])
TRAIN_CASES = {  # name: (model, memory saving, directions in the loss)
    "gns": (GNS, False, 1),
    "rgns": (RGNS, True, 2),
    "rgns_forward_only": (RGNS, True, 1),
    "rgns_plain": (RGNS, False, 2),
    "sep_gns": (SepGNS, False, 2),
}


def scene(particles: int, neighbours: float, seed: int = 0) -> tuple[dict, State]:
    """Uniform random particles in WaterDrop's box, the radius set for ``neighbours`` per particle."""
    generator = torch.Generator().manual_seed(seed)
    (low, high), _ = METADATA["bounds"]
    position = low + (high - low) * torch.rand(particles, 2, generator=generator)
    radius = math.sqrt(neighbours * (high - low) ** 2 / (particles * math.pi))
    for _ in range(2):  # fewer neighbours near the walls: correct the radius for the real count
        radius *= math.sqrt(neighbours * particles / radius_graph(position, radius).size(1))
    velocity = torch.tensor(METADATA["vel_std"]) * torch.randn(particles, 5, 2, generator=generator)
    metadata = dict(METADATA, default_connectivity_radius=radius)
    return metadata, State(position, velocity, torch.full((particles,), WATER))


def median_ms(fn, repeats: int, device: torch.device) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(1e3 * (time.perf_counter() - start))
    return statistics.median(times)


def train_step(model, state: State, edge_index: torch.Tensor, directions: int) -> None:
    model.zero_grad(set_to_none=True)
    graph = (state.particle_type, edge_index)
    history = state.velocity_history
    if directions == 2:  # as the training module does: both predictions in one call
        newest, oldest = model.both_velocities(state.position, history, history, *graph)
        loss = ((oldest - history[:, 0]) / model.acc_std_noisy).pow(2).mean()
    else:
        newest, loss = model.next_velocity(state.position, history, *graph), 0.0
    loss = loss + ((newest - history[:, -1]) / model.acc_std_noisy).pow(2).mean()
    loss.backward()


def build(case: str, metadata: dict, device: torch.device):
    cls, memory_saving, directions = TRAIN_CASES[case]
    model = cls(metadata).to(device)
    if cls is RGNS:
        model.processor.memory_saving = memory_saving
    with torch.no_grad():  # off the identity initialisation, as after training
        for parameter in model.parameters():
            parameter.add_(1e-2 * torch.randn_like(parameter))
    return model, directions


def _rss_mb(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"{field} not in /proc/self/status")


def peak_training_mb(case: str, particles: int, neighbours: float, device: str, queue) -> None:
    """Subprocess: rise of memory over one training step of ``case``."""
    torch.set_num_threads(1)
    device = torch.device(device)
    metadata, state = scene(particles, neighbours)
    state = state.to(device)
    model, directions = build(case, metadata, device)
    edge_index = model.graph(state.position)
    if device.type == "cuda":
        torch.cuda.synchronize()
        base = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
        train_step(model, state, edge_index, directions)
        torch.cuda.synchronize()
        queue.put((torch.cuda.max_memory_allocated() - base) / 2**20)
        return
    base = _rss_mb("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # reset the high-water mark to the current RSS
    train_step(model, state, edge_index, directions)
    queue.put(_rss_mb("VmHWM") - base)


def main(argv: list[str]) -> dict:
    parser = argparse.ArgumentParser(prog="python -m rgns.bench models", description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--neighbours", type=float, default=20.0)
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats after one warm-up (median)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    device = torch.device(args.device)
    metadata, state = scene(args.particles, args.neighbours)
    state = state.to(device)
    edge_index = GNS(metadata).graph(state.position)
    result = dict(scene=dict(particles=args.particles, edges=edge_index.size(1),
                             neighbours_per_particle=edge_index.size(1) / args.particles,
                             radius=metadata["default_connectivity_radius"], device=str(device),
                             threads=torch.get_num_threads(), repeats=args.repeats, torch=torch.__version__))

    result["params"] = {name: count_parameters(cls(metadata)) for name, cls in
                        (("gns", GNS), ("rgns", RGNS), ("sep_gns", SepGNS))}

    gns, _ = build("gns", metadata, device)
    rgns, _ = build("rgns", metadata, device)
    with torch.no_grad():
        result["infer_ms"] = dict(
            gns=median_ms(lambda: gns.step(state), args.repeats, device),
            rgns_forward=median_ms(lambda: rgns.step(state), args.repeats, device),
            rgns_inverse=median_ms(lambda: rgns.inverse_step(state), args.repeats, device),
        )
    del gns, rgns

    result["train_ms"] = {}
    for case in TRAIN_CASES:
        model, directions = build(case, metadata, device)
        result["train_ms"][case] = median_ms(lambda: train_step(model, state, edge_index, directions),
                                             args.repeats, device)
        del model

    context = multiprocessing.get_context("spawn")
    os.environ.setdefault("MALLOC_MMAP_THRESHOLD_", "65536")  # inherited by the spawned processes
    result["train_peak_mb"] = {}
    for case in TRAIN_CASES:
        queue = context.Queue()
        process = context.Process(target=peak_training_mb,
                                  args=(case, args.particles, args.neighbours, args.device, queue))
        process.start()
        result["train_peak_mb"][case] = queue.get()
        process.join()

    infer, train, peak = result["infer_ms"], result["train_ms"], result["train_peak_mb"]
    result["ratios"] = dict(
        rgns_forward_over_gns_infer=infer["rgns_forward"] / infer["gns"],
        rgns_inverse_over_forward_infer=infer["rgns_inverse"] / infer["rgns_forward"],
        rgns_over_gns_train=train["rgns"] / train["gns"],
        rgns_forward_only_over_gns_train=train["rgns_forward_only"] / train["gns"],
        rgns_over_gns_peak=peak["rgns"] / peak["gns"],
        rgns_over_sep_gns_train=train["rgns"] / train["sep_gns"],
        rgns_over_sep_gns_peak=peak["rgns"] / peak["sep_gns"],
    )
    print(table(result))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return result


def table(result: dict) -> str:
    s, p, i, t, m = (result[k] for k in ("scene", "params", "infer_ms", "train_ms", "train_peak_mb"))
    rows = [
        f"scene: {s['particles']} particles, {s['edges']} edges ({s['neighbours_per_particle']:.1f} per particle), "
        f"{s['device']}, {s['threads']} thread(s), median of {s['repeats']}",
        "",
        "| model | params | inference step (ms) | training step (ms) | peak training memory (MB) |",
        "|---|---|---|---|---|",
        f"| GNS | {p['gns'] / 1e6:.3f} M | {i['gns']:.0f} | {t['gns']:.0f} | {m['gns']:.0f} |",
        f"| R-GNS (forward + inverse loss) | {p['rgns'] / 1e6:.3f} M | {i['rgns_forward']:.0f} forward, "
        f"{i['rgns_inverse']:.0f} inverse | {t['rgns']:.0f} | {m['rgns']:.0f} |",
        f"| R-GNS† (forward loss only) | same | same | {t['rgns_forward_only']:.0f} | {m['rgns_forward_only']:.0f} |",
        f"| R-GNS without memory saving | same | same | {t['rgns_plain']:.0f} | {m['rgns_plain']:.0f} |",
        f"| Sep-GNS (both GNS, one loss each) | {p['sep_gns'] / 1e6:.3f} M | as GNS, per direction | "
        f"{t['sep_gns']:.0f} | {m['sep_gns']:.0f} |",
        "",
        "ratios: " + ", ".join(f"{k} {v:.2f}" for k, v in result["ratios"].items()),
    ]
    return "\n".join(rows)
