"""Where does a rollout's water meet the box? A simulator's forward rollouts against the truth at the walls.

The ground-truth solver keeps its particles off the walls (a layer of a millimetre or so on the
default scene). A simulator whose wall repulsion is too weak pushes particles into the floor,
where a hard wall (``model.hard_walls``) stops them: a dense layer on the floor that the truth
never has, and lost energy. This diagnostic rolls the simulator out from the forward task's start
frame of each trajectory and reports, at the chosen steps, beside the truth at the same frames:

- the closest any moving particle comes to a wall (negative: outside the box, without hard
  walls), and how many come within ``--near`` (a fraction of the connectivity radius) of one or
  beyond it;
- the mean height above the floor (the lower wall of the last axis);
- the rms speed per frame (water that has settled in the truth and still moves in the model, or
  an impact that splashes harder than the truth's);
- the rollout's error (mean over the particles of the squared distance, summed over the axes) and
  the share of it that is the centre of mass's (the bulk in the wrong place, not the shape)::

    python -m rgns.evaluation.walls CKPT [--steps 100 200 299] [--near 0.05] [--trajectories 8] \\
        [--json out.json] [--figure out.png --figure-trajectory 1]
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


def wall_figures(position: Tensor, bounds: Tensor, near: float) -> dict[str, float]:
    """Closest distance to a wall (negative outside the box), the fraction of particles within
    ``near`` of one or beyond it, and the mean height above the last axis's lower wall.

    Shapes: position ``[M, D]``, bounds ``[D, 2]``."""
    gap = torch.cat([position - bounds[:, 0], bounds[:, 1] - position], dim=-1).min(dim=-1).values  # [M]
    return dict(closest=float(gap.min()), near_fraction=float((gap < near).float().mean()),
                height=float((position[:, -1] - bounds[-1, 0]).mean()))


@torch.no_grad()
def rollout_from(model: Simulator, position: Tensor, particle_type: Tensor, start: int, last_step: int) -> Tensor:
    """The simulator's rollout from frame ``start`` (its history the true frames before it,
    kinematic particles on their true paths) to step ``last_step`` (counted from 0, the first
    predicted frame) or the trajectory's last frame, whichever comes first.

    Shapes: position ``[T, N, D]``, particle_type ``[N]``  ->  ``[S, N, D]``"""
    horizon = min(last_step + 1, len(position) - start - 1)
    if horizon < 1:
        raise ValueError(f"a trajectory of {len(position)} frames has no frame after the start frame {start}")
    state = State.from_positions(position[start - model.history : start + 1], particle_type)
    return model.rollout(state, horizon, position[start + 1 : start + 1 + horizon])


@torch.no_grad()
def at_the_walls(model: Simulator, position: Tensor, particle_type: Tensor, start: int, steps: list[int],
                 near: float, predicted: Tensor | None = None) -> list[dict]:
    """One row per step in ``steps`` (counted from 0, the first predicted frame, as the forward
    task's per-step errors) that the trajectory holds; ``predicted``, the model's rollout from
    ``start`` if already made (at least to ``max(steps)`` or the trajectory's end).

    Shapes: position ``[T, N, D]``, particle_type ``[N]``, predicted ``[S, N, D]``."""
    moving = particle_type != KINEMATIC
    if predicted is None:
        predicted = rollout_from(model, position, particle_type, start, max(steps))
    bounds = model.bounds.to(position)
    rows = []
    for step in (s for s in steps if s < len(predicted)):  # steps past the trajectory's end are left out
        mine, true = predicted[step][moving], position[start + 1 + step][moving]
        before = (predicted[step - 1] if step > 0 else position[start])[moving]  # the frame each came from
        error = float((mine - true).pow(2).sum(-1).mean())
        centre = float((mine.mean(0) - true.mean(0)).pow(2).sum())
        model, truth = wall_figures(mine, bounds, near), wall_figures(true, bounds, near)
        model["speed"] = rms_norm(mine - before)
        truth["speed"] = rms_norm(true - position[start + step][moving])
        rows.append(dict(step=step, model=model, truth=truth, error=error,
                         centre_share=centre / error if error > 0 else None))
    return rows


def snapshot_figure(model: Simulator, position: Tensor, particle_type: Tensor, start: int, steps: list[int],
                    path: Path, title: str, predicted: Tensor) -> None:
    """Truth (top) and simulator (bottom) at ``steps`` of one trajectory's rollout ``predicted``
    (:func:`rollout_from`), saved to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rgns.evaluation.plots import save_figure

    moving = particle_type != KINEMATIC
    steps = [s for s in steps if s < len(predicted)]
    bounds = model.bounds.cpu().numpy()
    fig, axes = plt.subplots(2, len(steps), figsize=(2.4 * len(steps), 5.0), squeeze=False)
    for column, step in enumerate(steps):
        for row, (frame, who) in enumerate(((position[start + 1 + step], "truth"), (predicted[step], title))):
            ax, frame = axes[row, column], frame[moving].cpu().numpy()
            ax.scatter(frame[:, 0], frame[:, -1], s=0.8)
            ax.set_xlim(*bounds[0]), ax.set_ylim(*bounds[-1]), ax.set_aspect("equal")
            ax.set_xticks([]), ax.set_yticks([])
            ax.set_title(f"{who}, step {step}", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> dict:
    from rgns.evaluation.methods import add_checkpoint_arguments, load_checkpoint_on_split
    from rgns.evaluation.tasks import mean_or_none

    parser = argparse.ArgumentParser(prog="python -m rgns.evaluation.walls", description=__doc__.split("\n\n")[0])
    add_checkpoint_arguments(parser)
    parser.add_argument("--steps", type=int, nargs="+", default=[100, 200, 299])
    parser.add_argument("--near", type=float, default=0.05, help="'near a wall': within this fraction of the radius")
    parser.add_argument("--hard-walls", choices=("checkpoint", "on", "off"), default="on",
                        help="the rollouts' hard walls: on (as the forward task scores), off, or as the checkpoint has them")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--figure", type=Path, default=None, help="truth and simulator side by side, one trajectory")
    parser.add_argument("--figure-trajectory", type=int, default=0)
    parser.add_argument("--figure-steps", type=int, nargs="+", default=[50, 100, 150, 200, 299])
    args = parser.parse_args(argv)
    if min(args.steps) < 0 or args.near <= 0:
        parser.error("--steps count from 0 and --near must be positive")
    torch.set_num_threads(1)
    model, root, dataset = load_checkpoint_on_split(args)
    if args.hard_walls != "checkpoint":
        model.hard_walls = args.hard_walls == "on"
    near = args.near * float(dataset.metadata["default_connectivity_radius"])
    if args.figure and not 0 <= args.figure_trajectory < len(dataset.trajectories):
        raise SystemExit(f"--figure-trajectory {args.figure_trajectory}: {len(dataset.trajectories)} trajectories loaded")
    figure_rollout = None
    try:
        rows = []
        for index, (p, t) in enumerate(dataset.trajectories):
            predicted = None
            if args.figure and index == args.figure_trajectory:  # one rollout serves the rows and the figure
                predicted = figure_rollout = rollout_from(model, p, t, dataset.start,
                                                          max(args.steps + args.figure_steps))
            rows.append(at_the_walls(model, p, t, dataset.start, args.steps, near, predicted))
    except ValueError as err:
        raise SystemExit(f"{root} ({args.split}): {err}") from None
    print(f"{args.checkpoint}: rollouts from frame {dataset.start} of {len(rows)} {args.split} trajectories of {root}, "
          f"hard walls {'on' if model.hard_walls else 'off'}; near: within {near:.3g} of a wall")
    summary = {}
    for step in args.steps:
        at = [row for rows_of in rows for row in rows_of if row["step"] == step]
        if not at:
            continue
        mean = {who: {key: mean_or_none(r[who][key] for r in at) for key in at[0][who]} for who in ("model", "truth")}
        mean["closest"] = {who: min(r[who]["closest"] for r in at) for who in ("model", "truth")}
        mean["error"] = mean_or_none(r["error"] for r in at)
        mean["centre_share"] = mean_or_none(r["centre_share"] for r in at)
        summary[step] = mean
        print(f"  step {step:>4} ({len(at)} trajectories): closest to a wall {mean['closest']['model']:.3g} (truth "
              f"{mean['closest']['truth']:.3g}); near a wall {100 * mean['model']['near_fraction']:.1f}% (truth "
              f"{100 * mean['truth']['near_fraction']:.1f}%); height {mean['model']['height']:.4f} (truth "
              f"{mean['truth']['height']:.4f}); rms speed {mean['model']['speed']:.3g} (truth "
              f"{mean['truth']['speed']:.3g}); error {mean['error']:.3g}, centre of mass "
              f"{100 * (mean['centre_share'] or 0):.0f}% of it")
    if args.figure:
        position, particle_type = dataset.trajectories[args.figure_trajectory]
        snapshot_figure(model, position, particle_type, dataset.start, args.figure_steps, args.figure,
                        f"{model.display_name or type(model).__name__}", figure_rollout)
        print(f"  figure: {args.figure}")
    result = dict(checkpoint=args.checkpoint, split=args.split, hard_walls=model.hard_walls, near=near,
                  summary=summary, trajectories=rows)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
