"""Training memory and time against depth: ``python -m rgns.bench depth [--depths 1 2 4 8 16]
[--latent 128] [--particles 1000] [--neighbours 20] [--repeats 3] [--chart PATH] [--json PATH]``.

One training step (forward, loss, backward) of each model at each depth, at a fixed width, on
the random 2D scene of ``python -m rgns.bench models`` (:func:`rgns.bench.models.scene`), with
that bench's training step (:func:`rgns.bench.models.train_step`, what the LightningModule
computes): GNS with its forward loss; R-GNS with the forward and the inverse loss on the same
batch through the memory-saving backward (its real training step); and, as the control, R-GNS
with the same losses through plain autograd (``memory_saving=False``). Depth is the models'
``layers``: GNS's interaction layers, R-GNS's reversible blocks (two couplings each, the paper's
count: 10 for both).

Peak memory is the rise of the resident set over one training step, gradients included
(:func:`rgns.evaluation.tasks.peak_memory_mb`: a forked copy, glibc's mmap threshold at 64 KiB,
the smaller of two calls after a warm-up); it is measured before any timing. Time is the median
of ``--repeats`` steps, the three models timed in turns at each depth
(:func:`rgns.bench.models.interleaved_median_ms`). One process, one thread. Printed: a row per
depth with each model's memory and time, memory against depth 1 for each model, and R-GNS's
memory against GNS's at the same depth.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from rgns.bench import models as bench_models
from rgns.bench.models import interleaved_median_ms, keep_freed_memory, scene, train_step
from rgns.evaluation.plots import save_figure, write_whole
from rgns.evaluation.tasks import peak_memory_mb
from rgns.models import count_parameters

CASES = {"gns": "GNS", "rgns": "R-GNS", "rgns_plain": "R-GNS, plain autograd"}  # TRAIN_CASES keys: labels


def build(case: str, metadata: dict, latent: int, layers: int) -> tuple[torch.nn.Module, int]:
    """The model of ``case`` (:data:`rgns.bench.models.TRAIN_CASES`) at this size, as the models
    bench builds it (weights off the identity initialisation), the draws seeded by the depth."""
    return bench_models.build(case, metadata, torch.device("cpu"), torch.Generator().manual_seed(layers),
                              latent=latent, layers=layers)


def measure(depths: list[int], latent: int, particles: int, neighbours: float, repeats: int,
            memory: bool = True, log=print) -> list[dict]:
    """A row per depth and model: ``{model, depth, parameters, peak_mb, ms}``."""
    metadata, state = scene(particles, neighbours)
    models = {(case, depth): build(case, metadata, latent, depth) for depth in depths for case in CASES}
    edge_index = next(iter(models.values()))[0].graph(state.position)

    def step(model, directions):
        def run():
            train_step(model, state, edge_index, directions)
            model.zero_grad(set_to_none=True)  # the gradients count in the step's memory, not in the base
        return run

    peaks = {}
    if memory:  # before the timing, which makes the process keep its freed memory
        for (case, depth), (model, directions) in models.items():
            peaks[case, depth] = peak_memory_mb(step(model, directions), torch.device("cpu"))
            log(f"memory: {CASES[case]}, depth {depth}: {peaks[case, depth]:.0f} MB", flush=True)
    keep_freed_memory()
    rows = []
    for depth in depths:
        times = interleaved_median_ms({case: step(*models[case, depth]) for case in CASES}, repeats,
                                      torch.device("cpu"))
        for case in CASES:
            rows.append(dict(model=CASES[case], case=case, depth=depth, latent=latent,
                             parameters=count_parameters(models[case, depth][0]), peak_mb=peaks.get((case, depth)),
                             ms=times[case], edges=int(edge_index.size(1)), particles=particles))
        log(f"time: depth {depth}: " + ", ".join(f"{CASES[c]} {times[c]:.0f} ms" for c in CASES), flush=True)
    return rows


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def table(rows: list[dict]) -> str:
    """A row per depth: each model's peak MB and ms, its memory over its own at the smallest depth,
    and R-GNS's memory over GNS's."""
    depths = sorted({r["depth"] for r in rows})
    at = {(r["case"], r["depth"]): r for r in rows}
    first = depths[0]

    def growth(case, depth):
        a, b = at[case, first]["peak_mb"], at[case, depth]["peak_mb"]
        return None if a is None or b is None or a <= 0 else b / a

    def ratio(depth):
        a, b = at["gns", depth]["peak_mb"], at["rgns", depth]["peak_mb"]
        return None if a is None or b is None or a <= 0 else b / a

    head = ["depth"] + [f"{CASES[c]} MB" for c in CASES] + [f"{CASES[c]} ms" for c in CASES] + \
        [f"{CASES[c]} MB / depth {first}" for c in CASES] + ["R-GNS MB / GNS MB"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for depth in depths:
        cells = [str(depth)] + [_fmt(at[c, depth]["peak_mb"], ".0f") for c in CASES] + \
            [_fmt(at[c, depth]["ms"], ".0f") for c in CASES] + [_fmt(growth(c, depth), ".2f") for c in CASES] + \
            [_fmt(ratio(depth), ".2f")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def chart(rows: list[dict], path: Path) -> None:
    """Peak training memory and time per step against depth, one line per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for case, label in CASES.items():
        mine = sorted((r for r in rows if r["case"] == case), key=lambda r: r["depth"])
        depths = [r["depth"] for r in mine]
        if all(r["peak_mb"] is not None for r in mine):
            left.plot(depths, [r["peak_mb"] for r in mine], "o-", label=label)
        right.plot(depths, [r["ms"] for r in mine], "o-", label=label)
    r = rows[0]
    for ax, ylabel in ((left, "peak training memory (MB)"), (right, "training step (ms)")):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("depth (layers)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle(f"one training step, latent {r['latent']}, {r['particles']} particles, {r['edges']} edges, 1 thread")
    save_figure(fig, path)


def main(argv: list[str]) -> list[dict]:
    parser = argparse.ArgumentParser(prog="python -m rgns.bench depth", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--depths", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    parser.add_argument("--latent", type=int, default=128, help="width of every model (the paper's: 128)")
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--neighbours", type=float, default=20.0)
    parser.add_argument("--repeats", type=int, default=3, help="timed rounds after one warm-up (median)")
    parser.add_argument("--memory", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--chart", type=Path, help="write a PNG of memory and time against depth here")
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args(argv)
    if min(args.depths) < 1:
        parser.error(f"--depths {args.depths}: every depth must be at least 1")
    torch.set_num_threads(1)
    torch.manual_seed(0)
    rows = measure(sorted(set(args.depths)), args.latent, args.particles, args.neighbours, args.repeats, args.memory)
    r = rows[0]
    print(f"\none training step, latent {r['latent']}, {r['particles']} particles, {r['edges']} edges, one thread, "
          f"median of {args.repeats} (models timed in turns); memory: rise of the resident set, gradients included\n")
    print(table(rows))
    if args.json:
        write_whole(args.json, (json.dumps(rows, indent=2) + "\n").encode())
    if args.chart:
        chart(rows, args.chart)
        print(f"chart: {args.chart}")
    return rows
