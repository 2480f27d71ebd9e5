"""Do a simulator's internal forces depend on how fast the water moves? One step from a true frame,
at the body's own speed and at other speeds.

A body of water in free fall has no internal forces: every particle accelerates alike, and so does
the whole body when it moves faster or slower (Galilean invariance). This diagnostic takes the
true state of each trajectory at ``--frame`` (on the default scene: early frames, before any
impact), moves every velocity of the history by the same amount so that the mean newest velocity
is ``speed`` times its own (0: the body momentarily at rest), and reports the root-mean-square of
the predicted acceleration less its mean over the particles: the **internal acceleration** the
simulator adds, in position units per frame squared, beside the truth's own at that frame and
gravity's size per frame squared, as yardsticks. Walls are as far as the frame has them (hard
walls off; a body near a wall feels it)::

    python -m rgns.evaluation.freefall CKPT [--frame 6] [--speeds 0 1 2] [--split test] [--trajectories 8] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from torch import Tensor

from rgns.data.contract import KINEMATIC
from rgns.evaluation.metrics import rms_norm
from rgns.models import Simulator, State
from rgns.models.base import dataset_gravity


def internal(acceleration: Tensor) -> float:
    """RMS of ``[M, D]`` accelerations less their mean over the particles."""
    return rms_norm(acceleration - acceleration.mean(0))


@torch.no_grad()
def internal_accelerations(model: Simulator, position: Tensor, particle_type: Tensor, frame: int,
                           speeds: list[float]) -> dict:
    """The simulator's internal acceleration at frame ``frame`` of one trajectory with its moving
    particles' velocities moved to ``speed`` times their mean newest velocity (for each of
    ``speeds``), the truth's at that frame, and the body's speed there.

    Shapes: position ``[T, N, D]``, particle_type ``[N]``."""
    k = model.history
    if not k <= frame < len(position) - 1:
        raise ValueError(f"--frame {frame}: needs {k} frames before it and one after it in a trajectory of "
                         f"{len(position)} frames")
    moving = particle_type != KINEMATIC
    state = State.from_positions(position[frame - k : frame + 1], particle_type)
    history = state.velocity_history  # [N, k, D]
    mean = history[moving, -1].mean(0)  # [D]: the body's newest velocity
    true = position[frame + 1] - 2 * position[frame] + position[frame - 1]
    rows = {}
    for speed in speeds:
        shift = torch.where(moving[:, None, None], (speed - 1) * mean, torch.zeros_like(mean))
        moved = State(state.position, history + shift, particle_type)
        step = model.step(moved)
        rows[speed] = internal((step.velocity_history[:, -1] - moved.velocity_history[:, -1])[moving])
    return dict(model=rows, truth=internal(true[moving]), speed=float(mean.norm()))


def main(argv: list[str] | None = None) -> dict:
    from rgns.evaluation.methods import add_checkpoint_arguments, load_checkpoint_on_split
    from rgns.evaluation.tasks import mean_or_none

    parser = argparse.ArgumentParser(prog="python -m rgns.evaluation.freefall", description=__doc__.split("\n\n")[0])
    add_checkpoint_arguments(parser)
    parser.add_argument("--frame", type=int, default=6, help="the true frame each step starts from")
    parser.add_argument("--speeds", type=float, nargs="+", default=[0.0, 1.0, 2.0],
                        help="the body's speed, as multiples of its own at --frame")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model, root, dataset = load_checkpoint_on_split(args)
    model.hard_walls = False
    try:
        rows = [internal_accelerations(model, p, t, args.frame, args.speeds) for p, t in dataset.trajectories]
    except ValueError as err:
        raise SystemExit(f"{root} ({args.split}): {err}") from None
    gravity = float(dataset_gravity(dataset.metadata).norm())
    summary = dict(model={speed: mean_or_none(row["model"][speed] for row in rows) for speed in args.speeds},
                   truth=mean_or_none(row["truth"] for row in rows),
                   speed=mean_or_none(row["speed"] for row in rows), gravity=gravity)
    print(f"{args.checkpoint}: one step from frame {args.frame} of {len(rows)} {args.split} trajectories of {root}; "
          f"rms internal acceleration (position units per frame^2), mean over the trajectories")
    for speed in args.speeds:
        print(f"  at {speed:g}x the body's speed: {summary['model'][speed]:.3g}  (per trajectory: "
              + " ".join(f"{row['model'][speed]:.2g}" for row in rows) + ")")
    print(f"  truth at its own speed ({summary['speed']:.3g} per frame): {summary['truth']:.3g}; "
          f"gravity per frame^2: {gravity:.3g}")
    result = dict(checkpoint=args.checkpoint, split=args.split, frame=args.frame, summary=summary,
                  trajectories=rows)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
