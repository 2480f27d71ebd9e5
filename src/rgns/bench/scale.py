"""Time and memory of a step against particle count, learned models and solvers side by side:
``python -m rgns.bench scale [--counts 1000 10000] [--dims 2 3] [--checkpoints A.ckpt ...]
[--no-models] [--no-solvers] [--steps 3] [--frames 10] [--chart PATH] [--json PATH]``.

For each dimension and count: a block of water on a lattice at the default scene's spacing
(6.5 mm; 2D) or Water-3D's (22 mm; 3D), in a box that holds it with room to fall, its radius
the scene's (15 mm, 35 mm: about 18 neighbours per particle in the bulk), every particle moving
with a random velocity of the default scene's spread (:func:`moving_state`).

Learned models: each is the checkpoint's configuration (default: the shipped R-GNS 128x2 and
GNS 64x4) built for that box and dimension (weights as initialised: time and memory do not depend
on their values), stepped in eval mode, radius graph included: median ms of ``--steps`` steps
after a warm-up, and the peak memory one step needs beyond the weights and the state
(``rgns.evaluation.tasks.peak_memory_mb``: the rise of the resident set in a forked copy).

Solvers: the project's solver of each dimension as its dataset runs it (:data:`SOLVER_SCENES`:
MLS-MPM of the ``waterdrop`` scene in 2D, WCSPH of the ``water3d`` scene in 3D, their substeps,
grid and material settings), built for the same box and count and started from the same block
and velocities: ms per frame of a rollout of ``--frames`` frames from the block (the state loaded
once, substeps and positions read back every frame, as a dataset's generation runs it), after a
warm-up frame that compiles its kernels; memory is the rise of the resident set from before the
solver is built to after its frames (the fields it allocates for its capacity, and its compiled
kernels), each (dimension, count) in a fresh process where an 8-particle solver of the same kind
ran first (Taichi's start-up is not counted).

One thread. A count whose graph would not fit in ``--max-edges`` is skipped, named. Printed:
a row per method and count, how each method's time grows with the count, and each model's time
per frame over the solver's at every count.
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import multiprocessing
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rgns.data.contract import WATER
from rgns.evaluation.methods import describe
from rgns.evaluation.plots import save_figure, write_whole
from rgns.evaluation.tasks import _status_mb, peak_memory_mb
from rgns.models import State
from rgns.training.module import SimulatorModule, _read_checkpoint

SCENES = {2: dict(spacing=0.0065, radius=0.015, dt=0.0025), 3: dict(spacing=0.022, radius=0.035, dt=0.005)}
SOLVER_SCENES = {2: "waterdrop", 3: "water3d"}  # conf/scene/: the solver each dimension's dataset is made with


def block(particles: int, dim: int) -> tuple[dict, Tensor]:
    """The metadata of a box and a lattice block of about ``particles`` in its lower middle."""
    spacing, radius, dt = (SCENES[dim][k] for k in ("spacing", "radius", "dt"))
    side = math.ceil(particles ** (1 / dim))
    axis = torch.arange(side, dtype=torch.float32) * spacing
    grid = torch.stack(torch.meshgrid(*[axis] * dim, indexing="ij"), -1).reshape(-1, dim)[:particles]
    extent = side * spacing
    low, high = 0.1, 0.1 + 2 * extent + 4 * radius  # room around the block
    position = grid + (0.1 + extent / 2 + 2 * radius)
    position[:, 1] -= extent / 2  # resting near the floor
    stats = [1e-3] * dim
    metadata = dict(bounds=[[low, high]] * dim, dim=dim, dt=dt, default_connectivity_radius=radius,
                    sequence_length=400, vel_mean=[0.0] * dim, vel_std=stats, acc_mean=[0.0] * dim,
                    acc_std=[1e-4] * dim, gravity=[0.0, -9.81] + [0.0] * (dim - 2))
    return metadata, position


def moving_state(position: Tensor, count: int, speed: float = 1e-3, seed: int = 0) -> State:
    """The block in motion: each particle's last 5 velocities a random one of about ``speed`` per
    frame (the default scene's velocity spread), not the special case of a block at rest."""
    velocity = speed * torch.randn(position.shape, generator=torch.Generator().manual_seed(seed))
    frames = torch.stack([position - (5 - k) * velocity for k in range(6)])
    return State.from_positions(frames, torch.full((count,), WATER))


def build(path: str, metadata: dict) -> tuple[torch.nn.Module, str]:
    """The checkpoint's model configuration built for ``metadata`` (weights as initialised), and its label."""
    hparams = _read_checkpoint(path, "checkpoint")["hyper_parameters"]
    module = SimulatorModule(model=hparams["model"], metadata=metadata, loss=hparams.get("loss"),
                             optimizer=hparams.get("optimizer"))
    return module.model.eval(), describe(hparams["model"])


def measure(model, state: State, steps: int) -> tuple[float, int]:
    """Median ms of one step over ``steps`` (after one warm-up), and the edges of its graph."""
    times = []
    with torch.no_grad():
        model.step(state)
        for _ in range(steps):
            begin = time.perf_counter()
            model.step(state)
            times.append(1e3 * (time.perf_counter() - begin))
        edges = int(model.graph(state.position).size(1))
    times.sort()
    return times[len(times) // 2], edges


def solver_label(dim: int) -> str:
    """``MLS-MPM (waterdrop, 10 substeps)``: the solver of :data:`SOLVER_SCENES` and its substeps per frame."""
    from rgns.data.generate import scene_config

    config = scene_config(SOLVER_SCENES[dim])["solver"]
    name = {"MPMSolver": "MLS-MPM", "SPHSolver": "WCSPH"}.get(config["_target_"].rsplit(".", 1)[-1], config["_target_"])
    return f"{name} ({SOLVER_SCENES[dim]}, {config['substeps']} substeps)"


def solver_frame(dim: int, count: int, frames: int, queue) -> None:
    """In a fresh process: ms per frame of a rollout of ``frames`` frames of the scene's solver from
    the moving block, and the rise of the resident set over building it and running its frames (MB)."""
    from hydra.utils import instantiate

    from rgns.data.generate import scene_config
    from rgns.physics.runtime import init_taichi

    try:
        torch.set_num_threads(1)
        init_taichi(num_threads=1)
        metadata, position = block(count, dim)
        velocity = moving_state(position, count).velocity_history[:, -1] / metadata["dt"]  # m/s
        position, velocity = position.numpy(), velocity.numpy()
        material = np.full(count, WATER)
        config = dict(scene_config(SOLVER_SCENES[dim]), bounds=metadata["bounds"], capacity=count)
        scene = instantiate(config, _convert_="all")
        _, small = block(8, dim)  # Taichi's one-time start-up (its runtime, the compiler) outside the measurement
        instantiate(dict(config, capacity=8), _convert_="all").solver.rollout(small.numpy(), 0 * small.numpy(),
                                                                              material[:8], 2)
        base = _status_mb("VmRSS")
        Path("/proc/self/clear_refs").write_text("5")  # reset the high-water mark to the current RSS
        solver = scene.solver
        solver.rollout(position, velocity, material, 2)  # compiles the kernels
        begin = time.perf_counter()
        solver.rollout(position, velocity, material, frames + 1)  # the block, then `frames` frames
        queue.put((1e3 * (time.perf_counter() - begin) / frames, _status_mb("VmHWM") - base))
    except Exception as error:  # noqa: BLE001 - reported to the parent, which raises it with the case
        queue.put(repr(error))


def measure_solver(dim: int, count: int, frames: int) -> tuple[float, float]:
    """:func:`solver_frame` in a spawned process: ``(ms per frame, peak MB)``."""
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=solver_frame, args=(dim, count, frames, queue))
    process.start()
    result = queue.get()
    process.join()
    if isinstance(result, str):
        raise RuntimeError(f"{solver_label(dim)} at {count} particles in {dim}D failed: {result}")
    return result


def chart(rows: list[dict], path: Path) -> None:
    """Time per frame and memory against particles, one panel per dimension and quantity (log-log)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dims = sorted({r["dim"] for r in rows})
    fig, axes = plt.subplots(2, len(dims), figsize=(5.5 * len(dims), 8), squeeze=False)
    for column, dim in enumerate(dims):
        for label in dict.fromkeys(r["model"] for r in rows if r["dim"] == dim):
            mine = [r for r in rows if r["dim"] == dim and r["model"] == label]
            style = "s--" if mine[0]["kind"] == "solver" else "o-"
            axes[0, column].plot([r["particles"] for r in mine], [r["ms_per_step"] for r in mine], style, label=label)
            memory = [r for r in mine if r["peak_mb"] is not None]
            if memory:
                axes[1, column].plot([r["particles"] for r in memory], [r["peak_mb"] for r in memory], style,
                                     label=label)
        for row, ylabel in enumerate(("ms per frame (one thread)", "peak memory (MB)")):
            ax = axes[row, column]
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("particles")
            ax.set_ylabel(ylabel)
            ax.set_title(f"{dim}D")
            ax.grid(alpha=0.3, which="both")
            if ax.lines:
                ax.legend(fontsize=8)
    save_figure(fig, path)


def main(argv: list[str]) -> list[dict]:
    parser = argparse.ArgumentParser(prog="python -m rgns.bench scale", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--counts", type=int, nargs="+", default=[1000, 10000],
                        help="particle counts (10^5 and more by option: --counts 1000 10000 100000)")
    parser.add_argument("--dims", type=int, nargs="+", default=[2, 3], choices=[2, 3])
    parser.add_argument("--checkpoints", nargs="+", default=None,
                        help="model configurations (default: pretrained/waterdrop40_main_64/*.ckpt)")
    parser.add_argument("--models", action=argparse.BooleanOptionalAction, default=True,
                        help="time the learned models (--no-models: the solvers only)")
    parser.add_argument("--solvers", action=argparse.BooleanOptionalAction, default=True,
                        help="time each dimension's solver (MPM in 2D, WCSPH in 3D) at the same counts")
    parser.add_argument("--steps", type=int, default=3, help="timed steps of each model (median)")
    parser.add_argument("--frames", type=int, default=10, help="frames of each solver's timed rollout")
    parser.add_argument("--memory", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--max-edges", type=float, default=5e7, help="skip a scene whose graph has more edges")
    parser.add_argument("--chart", type=Path, help="write a PNG of time and memory against particles here")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    paths = (args.checkpoints or sorted(glob.glob("pretrained/waterdrop40_main_64/*.ckpt"))) if args.models else []
    if args.models and not paths:
        parser.error("no checkpoints: pass --checkpoints (or --no-models)")
    if not paths and not args.solvers:
        parser.error("nothing to time: --no-models and --no-solvers")
    rows = []
    print(f"{'method':<34} {'dim':>3} {'particles':>9} {'edges':>10} {'ms/frame':>9} {'peak MB':>8}", flush=True)

    def report(row):
        rows.append(row)
        edges = "-" if row["edges"] is None else row["edges"]
        peak = "-" if row["peak_mb"] is None else f"{row['peak_mb']:.0f}"
        print(f"{row['model']:<34} {row['dim']:>3} {row['particles']:>9} {edges:>10} {row['ms_per_step']:>9.1f} "
              f"{peak:>8}", flush=True)

    for dim in args.dims:
        for count in args.counts:
            metadata, position = block(count, dim)
            expected = count * 18
            if paths and expected > args.max_edges:
                print(f"{dim}D, {count} particles: about {expected:.2g} edges, over --max-edges: models skipped")
            elif paths:
                state = moving_state(position, count)
                for path in paths:
                    model, label = build(path, metadata)
                    ms, edges = measure(model, state, args.steps)
                    peak = None
                    if args.memory:
                        with torch.no_grad():
                            peak = peak_memory_mb(lambda: model.step(state), torch.device("cpu"))
                    report(dict(model=label, kind="model", source=path, dim=dim, particles=count, edges=edges,
                                ms_per_step=ms, peak_mb=peak))
            if args.solvers:
                ms, peak = measure_solver(dim, count, args.frames)
                peak = peak if args.memory else None
                report(dict(model=solver_label(dim), kind="solver", source=f"conf/scene/{SOLVER_SCENES[dim]}.yaml",
                            dim=dim, particles=count, edges=None, ms_per_step=ms, peak_mb=peak))
    for dim in args.dims:  # how the step grows: the exponent between the smallest and largest count
        for label in dict.fromkeys(r["model"] for r in rows):
            mine = [r for r in rows if r["dim"] == dim and r["model"] == label]
            if len(mine) > 1:
                a, b = mine[0], mine[-1]
                slope = math.log(b["ms_per_step"] / a["ms_per_step"]) / math.log(b["particles"] / a["particles"])
                print(f"{label}, {dim}D: time grows as particles^{slope:.2f} from {a['particles']} to {b['particles']}")
    for dim in args.dims:  # each model against the solver, count by count
        solvers = {r["particles"]: r for r in rows if r["dim"] == dim and r["kind"] == "solver"}
        for r in rows:
            if r["dim"] == dim and r["kind"] == "model" and r["particles"] in solvers:
                s = solvers[r["particles"]]
                print(f"{dim}D, {r['particles']} particles: {r['model']} takes {r['ms_per_step'] / s['ms_per_step']:.1f}x "
                      f"the time per frame of {s['model']}")
    if args.json:
        write_whole(args.json, json.dumps(rows, indent=2).encode())
    if args.chart:
        chart(rows, args.chart)
        print(f"chart: {args.chart}")
    return rows
