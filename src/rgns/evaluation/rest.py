"""Does a settled pool stay settled? A simulator's rollout from the last true frame of each trajectory.

The last frames of a trajectory hold water that has (nearly) come to rest. A simulator that has
learned the fluid's pressure keeps it there; one whose pressure is too weak lets it sink into a
denser layer, which the rollout error alone shows only as a growing error late in the rollouts.
This diagnostic rolls the simulator out ``steps`` steps from the last true frame (its history the
true frames before it) and reports, averaged over the trajectories:

- the mean number of neighbours within the connectivity radius at the end over that of the start
  frame (1: the density is kept; above 1: compressed),
- the root-mean-square displacement of the particles from the start frame,
- the same two figures for the truth over its own last ``steps`` frames, as the yardstick of how
  settled the start frame is::

    python -m rgns.evaluation.rest CKPT [--steps 100] [--split test] [--trajectories 8] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from torch import Tensor

from rgns.data.contract import KINEMATIC
from rgns.evaluation.metrics import density_ratio
from rgns.models import Simulator, State


def drift(start: Tensor, end: Tensor, radius: float) -> dict[str, float | None]:
    """Density change (``None`` where :func:`density_ratio` has none) and displacement from
    ``start`` to ``end`` (``[M, D]`` moving particles)."""
    return dict(neighbours_ratio=density_ratio(end, start, radius),
                rms_displacement=float((end - start).pow(2).sum(-1).mean().sqrt()))


@torch.no_grad()
def settled_pool(model: Simulator, position: Tensor, particle_type: Tensor, steps: int, radius: float) -> dict:
    """The simulator's and the truth's drift over ``steps`` steps from the last frame.

    Shapes: position ``[T, N, D]`` (T > steps and T > history), particle_type ``[N]``."""
    k, last = model.history, len(position) - 1
    if last < max(k, steps):
        raise ValueError(f"a trajectory of {len(position)} frames is too short to compare {steps} steps at rest")
    moving = particle_type != KINEMATIC
    state = State.from_positions(position[last - k : last + 1], particle_type)
    kinematic = position[last : last + 1].expand(steps, -1, -1)  # walls and obstacles hold their last place
    predicted = model.rollout(state, steps, kinematic)
    return dict(model=drift(position[last][moving], predicted[-1][moving], radius),
                truth=drift(position[last - steps][moving], position[last][moving], radius))


def main(argv: list[str] | None = None) -> dict:
    from rgns.evaluation.methods import add_checkpoint_arguments, load_checkpoint_on_split
    from rgns.evaluation.tasks import mean_or_none

    parser = argparse.ArgumentParser(prog="python -m rgns.evaluation.rest", description=__doc__.split("\n\n")[0])
    add_checkpoint_arguments(parser)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error(f"--steps {args.steps}: roll out at least 1 step")
    torch.set_num_threads(1)
    model, root, dataset = load_checkpoint_on_split(args)
    radius = float(dataset.metadata["default_connectivity_radius"])
    try:
        rows = [settled_pool(model, p, t, args.steps, radius) for p, t in dataset.trajectories]
    except ValueError as err:
        raise SystemExit(f"{root} ({args.split}): {err}; lower --steps") from None
    summary = {who: {key: mean_or_none(row[who][key] for row in rows) for key in rows[0][who]}
               for who in ("model", "truth")}
    print(f"{args.checkpoint}: {args.steps} steps from the last frame of {len(rows)} {args.split} trajectories of {root}")
    for who, label in (("model", "simulator, from the last frame"), ("truth", f"truth, its last {args.steps} frames")):
        print(f"  {label:<32} neighbours x{_figure(summary[who]['neighbours_ratio'], 3)}  "
              f"rms displacement {_figure(summary[who]['rms_displacement'], 4)}  (per trajectory: "
              + " ".join(f"x{_figure(row[who]['neighbours_ratio'], 2)}" for row in rows) + ")")
    result = dict(checkpoint=args.checkpoint, split=args.split, steps=args.steps, summary=summary, trajectories=rows)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return result


def _figure(value: float | None, digits: int) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


if __name__ == "__main__":
    main()
