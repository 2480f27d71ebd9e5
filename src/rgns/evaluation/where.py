"""Where does a rollout lose? Its error step by step on each trajectory, and where its worst particles are.

A rollout's mean error can come from one trajectory and, within it, from one event (a wave
running along the floor, a splash up a wall). This diagnostic rolls a simulator out as the
forward task does (from the true state at ``t0``, the walls and obstacles at their true places)
and prints, for each trajectory and every ``--every`` steps:

- the squared position error at that step (the forward task's rollout MSE is its mean over the steps),
- the share of the rollout's summed error reached by that step (where the error is made),
- the mean true and predicted position of the ``--worst`` particles with the largest error there
  (which water is wrong, and which way)::

    python -m rgns.evaluation.where CKPT [--data-root DIR] [--trajectories 8] [--only 1] [--steps 300]
        [--every 25] [--worst 20] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from torch import Tensor

from rgns.data.contract import KINEMATIC
from rgns.evaluation.metrics import mse_per_step, with_last
from rgns.training.rollouts import forward_rollout


def error_steps(predicted: Tensor, truth: Tensor, particle_type: Tensor, every: int, worst: int) -> dict:
    """The per-step figures of one rollout.

    Shapes: predicted, truth ``[T, N, D]`` (frames t0 + 1 ... t0 + T), particle_type ``[N]``.
    Returns ``rollout_mse`` (the mean over the steps, as the forward task's) and ``rows``: for
    steps ``every, 2 every, ...`` (1-based, the last step always included) the step's ``mse``, the
    ``share`` of the summed error reached by it, and the mean ``truth`` and ``predicted``
    position of the ``worst`` moving particles with the largest squared error at that step."""
    if every < 1 or worst < 1:
        raise ValueError(f"every={every}, worst={worst}: both at least 1")
    per_step = mse_per_step(predicted, truth)  # [T]
    cumulative = per_step.cumsum(0)
    total = float(cumulative[-1])
    moving = (particle_type != KINEMATIC).nonzero().squeeze(1)
    steps = with_last(list(range(every, len(per_step) + 1, every)), len(per_step))
    rows = []
    for step in steps:
        error = (predicted[step - 1, moving] - truth[step - 1, moving]).pow(2).sum(-1)  # [M]
        chosen = moving[error.argsort(descending=True)[:worst]]
        rows.append(dict(step=step, mse=float(per_step[step - 1]),
                         share=float(cumulative[step - 1]) / total if total > 0 else None,
                         truth=truth[step - 1, chosen].mean(0).tolist(),
                         predicted=predicted[step - 1, chosen].mean(0).tolist()))
    return dict(rollout_mse=float(per_step.mean()), rows=rows)


def main(argv: list[str] | None = None) -> dict:
    from rgns.evaluation.methods import add_checkpoint_arguments, load_checkpoint_on_split

    parser = argparse.ArgumentParser(prog="python -m rgns.evaluation.where", description=__doc__.split("\n\n")[0])
    add_checkpoint_arguments(parser)
    parser.add_argument("--only", type=int, nargs="*", default=None,
                        help="trajectory numbers to roll out (default: every one of --trajectories)")
    parser.add_argument("--steps", type=int, default=300, help="rollout length, capped by each trajectory's")
    parser.add_argument("--every", type=int, default=25)
    parser.add_argument("--worst", type=int, default=20)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.steps < 1 or args.every < 1 or args.worst < 1:
        parser.error(f"--steps {args.steps} --every {args.every} --worst {args.worst}: each at least 1")
    torch.set_num_threads(1)
    model, root, dataset = load_checkpoint_on_split(args)
    chosen = range(len(dataset.trajectories)) if args.only is None else args.only
    missing = [i for i in chosen if not 0 <= i < len(dataset.trajectories)]
    if missing:
        parser.error(f"--only {missing}: {root} ({args.split}) has trajectories 0..{len(dataset.trajectories) - 1} "
                     f"loaded (raise --trajectories)")
    start, rows = dataset.start, {}
    print(f"{args.checkpoint} on {root} ({args.split}): squared position error (1e-3) from frame {start}; "
          f"share: of the rollout's summed error, reached by that step; worst {args.worst}: the mean true and "
          f"predicted position of the particles with the largest error there")
    for i in chosen:
        position, particle_type = dataset.trajectories[i]
        steps = min(args.steps, len(position) - 1 - start)
        if steps < 1:
            raise SystemExit(f"{root} ({args.split}): trajectory {i} is too short to roll out from frame {start}")
        predicted = forward_rollout(model, position, particle_type, start, steps)
        rows[i] = error_steps(predicted, position[start + 1 : start + 1 + steps], particle_type, args.every, args.worst)
        print(f"trajectory {i} ({position.shape[1]} particles): rollout MSE {rows[i]['rollout_mse'] * 1e3:.3f}")
        for row in rows[i]["rows"]:
            share = "—" if row["share"] is None else f"{row['share']:.2f}"
            print(f"  step {row['step']:4d}  {row['mse'] * 1e3:8.3f}  share {share}  worst {args.worst}: truth "
                  + _point(row["truth"]) + "  predicted " + _point(row["predicted"]))
    result = dict(checkpoint=args.checkpoint, root=str(root), split=args.split, start=start, trajectories=rows)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return result


def _point(values: list[float]) -> str:
    return "(" + ", ".join(f"{v:.3f}" for v in values) + ")"


if __name__ == "__main__":
    main()
