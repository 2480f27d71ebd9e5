"""Cost of the simulators at the paper's sizes: ``python -m rgns.bench models --json PATH``.

One process, one thread, one random 1,000-particle 2D scene (about 20 neighbours per particle)
shared by every model. Reports parameters, inference step (``step`` / ``inverse_step``, radius
graph included), training step (forward, loss, backward) and peak training memory. The cases
compared in a ratio are timed in turns (one of each per round, median over the rounds), so the
ratios hold on a machine whose speed drifts; on the CPU the timing process keeps freed memory
(:func:`keep_freed_memory`), so page faults do not add noise. Peak memory
on the CPU is the rise of the resident set over one training step, each model measured in a
fresh subprocess with glibc's mmap threshold fixed at 64 KiB, so that freed tensors leave the
resident set at once (on CUDA, ``torch.cuda.max_memory_allocated``).

Training steps: GNS with its forward loss; R-GNS with the forward and the inverse loss on the
same batch (its real training step, memory-saving backward), plus R-GNS† (forward loss only),
R-GNS without memory saving, and Sep-GNS (both of its GNS, one loss each: the other way to
train both directions) for reference; the paper's other forward baselines, EGNN, NeuralSPH and
DMCF, with their forward loss (one step; DMCF's unrolled training multiplies it by the window).
Inference steps run in eval mode, so NeuralSPH's includes its SPH relaxation.
"""
from __future__ import annotations

import argparse
import ctypes
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
from rgns.models import DMCF, EGNN, GNS, RGNS, NeuralSPH, SepGNS, State, count_parameters

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
    "egnn": (EGNN, False, 1),
    "neural_sph": (NeuralSPH, False, 1),
    "dmcf": (DMCF, False, 1),
}
FORWARD_BASELINES = {"egnn": "EGNN", "neural_sph": "NeuralSPH", "dmcf": "DMCF"}  # rows after Sep-GNS


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


def keep_freed_memory() -> bool:
    """Ask glibc to keep freed memory in the process (no trimming, no mmap for large blocks), so
    that timings measure the kernels rather than the page faults of memory handed back to the
    system and taken again at every step (which varied inference times by up to 1.8x here).
    Returns whether it applied (glibc only)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    return bool(libc.mallopt(m_mmap_threshold, 1 << 30)) and bool(libc.mallopt(m_trim_threshold, 1 << 30))


def interleaved_median_ms(fns: dict, repeats: int, device: torch.device) -> dict[str, float]:
    """Median wall time of each function, timed in turns after one warm-up each: one call of each
    per round, the order rotated every round (A B C, B C A, C A B, ...), so that a slow spell of a
    shared machine, or the cost of following a particular call, falls on every function alike."""
    for fn in fns.values():
        fn()
    times = {name: [] for name in fns}
    names = list(fns)
    for round_ in range(repeats):
        for name in names[round_ % len(names):] + names[: round_ % len(names)]:
            fn = fns[name]
            if device.type == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
            fn()
            if device.type == "cuda":
                torch.cuda.synchronize()
            times[name].append(1e3 * (time.perf_counter() - start))
    return {name: statistics.median(values) for name, values in times.items()}


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


def build(case: str, metadata: dict, device: torch.device, generator: torch.Generator | None = None, **size):
    """The model of ``case`` (its class's default size, or ``size``: ``latent=``, ``layers=``), its
    weights moved off the identity initialisation as after training (by ``generator``'s draws where
    given), and the directions of its loss."""
    cls, memory_saving, directions = TRAIN_CASES[case]
    model = cls(metadata, **size).to(device)
    if cls is RGNS:
        model.processor.memory_saving = memory_saving
    with torch.no_grad():  # off the identity initialisation, as after training
        for parameter in model.parameters():
            noise = torch.randn_like(parameter) if generator is None else \
                torch.randn(parameter.shape, generator=generator).to(parameter.device)
            parameter.add_(1e-2 * noise)
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
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds after one warm-up (median)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    device = torch.device(args.device)
    kept = keep_freed_memory() if device.type == "cpu" else False
    metadata, state = scene(args.particles, args.neighbours)
    state = state.to(device)
    edge_index = GNS(metadata).graph(state.position)
    result = dict(scene=dict(particles=args.particles, edges=edge_index.size(1),
                             neighbours_per_particle=edge_index.size(1) / args.particles,
                             radius=metadata["default_connectivity_radius"], device=str(device),
                             threads=torch.get_num_threads(), repeats=args.repeats, torch=torch.__version__,
                             freed_memory_kept=kept))

    result["params"] = {name: count_parameters(TRAIN_CASES[name][0](metadata))
                        for name in ("gns", "rgns", "sep_gns", *FORWARD_BASELINES)}

    gns, _ = build("gns", metadata, device)
    rgns, _ = build("rgns", metadata, device)
    others = {name: build(name, metadata, device)[0].eval() for name in FORWARD_BASELINES}
    with torch.no_grad():
        result["infer_ms"] = interleaved_median_ms(dict(
            gns=lambda: gns.step(state),
            rgns_forward=lambda: rgns.step(state),
            rgns_inverse=lambda: rgns.inverse_step(state),
            **{name: (lambda m=model: m.step(state)) for name, model in others.items()},
        ), args.repeats, device)
    del gns, rgns, others

    models = {case: build(case, metadata, device) for case in TRAIN_CASES}
    result["train_ms"] = interleaved_median_ms(
        {case: (lambda m=model, d=directions: train_step(m, state, edge_index, d))
         for case, (model, directions) in models.items()}, args.repeats, device)
    del models

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
        **{f"{name}_over_gns_infer": infer[name] / infer["gns"] for name in FORWARD_BASELINES},
        **{f"{name}_over_gns_train": train[name] / train["gns"] for name in FORWARD_BASELINES},
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
        f"{s['device']}, {s['threads']} thread(s), median of {s['repeats']} rounds, cases timed in turns",
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
        *(f"| {label} | {p[name] / 1e6:.3f} M | {i[name]:.0f} | {t[name]:.0f} | {m[name]:.0f} |"
          for name, label in FORWARD_BASELINES.items()),
        "",
        "ratios: " + ", ".join(f"{k} {v:.2f}" for k, v in result["ratios"].items()),
    ]
    return "\n".join(rows)
