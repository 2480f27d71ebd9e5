"""Where a simulator's physics is wrong: its one-step acceleration on the true states.

A rollout's error mixes what the network gets wrong with how that compounds. This diagnostic
feeds every true state ``(p^t, V^t)`` of a trajectory to the simulator and compares the
acceleration it predicts, ``v^{t+1} - v^t``, with the true one, ``p^{t+1} - 2 p^t + p^{t-1}``,
frame by frame: in free fall it should be gravity, at an impact many times that, in a settled pool
nearly zero. The frames are grouped in spans of the trajectory (by default 5-30, 30-60, 60-100,
100-200 and 200 to the end: free fall and first impacts, the splash, the sloshing, settling)::

    python -m rgns.evaluation.onestep CKPT [--split test] [--trajectories 8] [--json out.json]

The root-mean-square accelerations are over the moving particles, in position units per frame
squared (the default scene's gravity is 6.1e-5).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from torch import Tensor

from rgns.data.contract import KINEMATIC
from rgns.models import Simulator, State

SPANS = (5, 30, 60, 100, 200)  # the first frame of each span; the last runs to the end


@torch.no_grad()
def one_step_accelerations(model: Simulator, position: Tensor, particle_type: Tensor) -> dict[str, Tensor]:
    """True and predicted accelerations at every frame with a full history and a next frame.

    Shapes:
        position: ``[T, N, D]``, particle_type: ``[N]``  ->  ``frame [F]``, ``true``, ``predicted``
        ``[F, M, D]`` over the M moving particles (F = T - k - 1 frames, t = k .. T - 2)
    """
    k, moving = model.history, particle_type != KINEMATIC
    frames, true, predicted = [], [], []
    for t in range(k, len(position) - 1):
        state = State.from_positions(position[t - k : t + 1], particle_type)
        velocity = model.next_velocity(state.position, state.velocity_history, particle_type, model.graph(state.position))
        frames.append(t)
        true.append((position[t + 1] - 2 * position[t] + position[t - 1])[moving])
        predicted.append((velocity - state.velocity_history[:, -1])[moving])
    return dict(frame=torch.tensor(frames), true=torch.stack(true), predicted=torch.stack(predicted))


def rms(values: Tensor) -> float:
    """Root mean square of the vectors' norms. ``[..., D] -> float``"""
    return float(values.pow(2).sum(-1).mean().sqrt())


def by_span(trajectories: list[dict[str, Tensor]], spans=SPANS) -> list[dict]:
    """Per span of frames, over every trajectory: rms of the true and predicted accelerations, of
    their difference, and that error over the true rms."""
    rows = []
    for first, end in zip(spans, (*spans[1:], None)):
        last = float("inf") if end is None else end
        picked = [{key: a[key][(a["frame"] >= first) & (a["frame"] < last)] for key in ("true", "predicted")}
                  for a in trajectories]
        true = torch.cat([p["true"].flatten(0, 1) for p in picked])
        if len(true) == 0:
            continue
        predicted = torch.cat([p["predicted"].flatten(0, 1) for p in picked])
        error = rms(predicted - true)
        rows.append(dict(frames=f"{first}-{'end' if end is None else end}", true_rms=rms(true),
                         predicted_rms=rms(predicted), error_rms=error, relative_error=error / rms(true)))
    return rows


def main(argv: list[str] | None = None) -> list[dict]:
    from rgns.evaluation.methods import add_checkpoint_arguments, load_checkpoint_on_split

    parser = argparse.ArgumentParser(prog="python -m rgns.evaluation.onestep", description=__doc__.split("\n\n")[0])
    add_checkpoint_arguments(parser)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model, root, dataset = load_checkpoint_on_split(args)
    rows = by_span([one_step_accelerations(model, p, t) for p, t in dataset.trajectories])
    print(f"{args.checkpoint}: one-step accelerations on {len(dataset.trajectories)} {args.split} trajectories of {root}")
    print(f"{'frames':<10}{'true rms':>12}{'predicted rms':>15}{'error rms':>12}{'error / true':>14}")
    for row in rows:
        print(f"{row['frames']:<10}{row['true_rms']:>12.2e}{row['predicted_rms']:>15.2e}{row['error_rms']:>12.2e}"
              f"{row['relative_error']:>14.2f}")
    if args.json:
        args.json.write_text(json.dumps(dict(checkpoint=args.checkpoint, split=args.split, spans=rows), indent=1))
    return rows


if __name__ == "__main__":
    main()
