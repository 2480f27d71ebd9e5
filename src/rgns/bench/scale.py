"""Time and memory of a rollout step against particle count: ``python -m rgns.bench scale
[--counts 1000 10000 100000] [--dims 2 3] [--checkpoints A.ckpt ...] [--steps 3] [--json PATH]``.

For each dimension and count: a block of water on a lattice at the default scene's spacing
(6.5 mm; 2D) or Water-3D's (22 mm; 3D), in a box that holds it with room to fall, its radius
the scene's (15 mm, 35 mm: about 18 neighbours per particle in the bulk), every particle moving
with a random velocity of the default scene's spread (:func:`moving_state`). Each model is the checkpoint's configuration (default: the shipped
R-GNS 128x2 and GNS 64x4) built for that box and dimension (weights as initialised: time and
memory do not depend on their values), stepped in eval mode, radius graph included: median ms of
``--steps`` steps after a warm-up, and the peak memory one step needs beyond the weights and the
state (``rgns.evaluation.tasks.peak_memory_mb``: the rise of the resident set in a forked copy).
One process, one thread. A count whose graph would not fit in ``--max-edges`` is skipped, named.
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import time

import torch
from torch import Tensor

from rgns.data.contract import WATER
from rgns.evaluation.methods import describe
from rgns.evaluation.plots import write_whole
from rgns.evaluation.tasks import peak_memory_mb
from rgns.models import State
from rgns.training.module import SimulatorModule, _read_checkpoint

SCENES = {2: dict(spacing=0.0065, radius=0.015, dt=0.0025), 3: dict(spacing=0.022, radius=0.035, dt=0.005)}


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


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--counts", type=int, nargs="+", default=[1000, 10000, 100000])
    parser.add_argument("--dims", type=int, nargs="+", default=[2, 3], choices=[2, 3])
    parser.add_argument("--checkpoints", nargs="+", default=None,
                        help="model configurations (default: pretrained/waterdrop40_main_64/*.ckpt)")
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--memory", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--max-edges", type=float, default=5e7, help="skip a scene whose graph has more edges")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    paths = args.checkpoints or sorted(glob.glob("pretrained/waterdrop40_main_64/*.ckpt"))
    if not paths:
        parser.error("no checkpoints: pass --checkpoints")
    rows = []
    print(f"{'model':<28} {'dim':>3} {'particles':>9} {'edges':>10} {'ms/step':>9} {'peak MB':>8}", flush=True)
    for dim in args.dims:
        for count in args.counts:
            metadata, position = block(count, dim)
            expected = count * 18
            if expected > args.max_edges:
                print(f"{dim}D, {count} particles: about {expected:.2g} edges, over --max-edges: skipped")
                continue
            state = moving_state(position, count)
            for path in paths:
                model, label = build(path, metadata)
                ms, edges = measure(model, state, args.steps)
                peak = None
                if args.memory:
                    with torch.no_grad():
                        peak = peak_memory_mb(lambda: model.step(state), torch.device("cpu"))
                rows.append(dict(model=label, source=path, dim=dim, particles=count, edges=edges, ms_per_step=ms,
                                 peak_mb=peak))
                print(f"{label:<28} {dim:>3} {count:>9} {edges:>10} {ms:>9.1f} "
                      f"{'-' if peak is None else f'{peak:.0f}':>8}", flush=True)
    for dim in args.dims:  # how the step grows: the exponent between the smallest and largest count
        for label in dict.fromkeys(r["model"] for r in rows):
            mine = [r for r in rows if r["dim"] == dim and r["model"] == label]
            if len(mine) > 1:
                a, b = mine[0], mine[-1]
                slope = math.log(b["ms_per_step"] / a["ms_per_step"]) / math.log(b["particles"] / a["particles"])
                print(f"{label}, {dim}D: time grows as particles^{slope:.2f} from {a['particles']} to {b['particles']}")
    if args.json:
        write_whole(args.json, json.dumps(rows, indent=2).encode())
