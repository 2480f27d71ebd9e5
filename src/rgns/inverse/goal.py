"""Goal-conditioned shaping: steer a fluid into a target shape (the paper's letters "L" and "N").

A target is given as text, an image mask or a point file, and becomes particles at the dataset's
spacing, placed in the box, **at rest** (every slot of the velocity history zero: the goal is the
shape standing still at frame K; no settling step is run, so the target is exactly the shape
asked for). Then, per method:

- a bidirectional learned simulator (R-GNS, Sep-GNS): K inverse steps from the target to an
  inferred initial state, then K forward steps from it to the reproduced state;
- the optimisation baseline (differentiable SPH + Adam, :mod:`rgns.inverse.optimise`): the
  initial state found by Adam from the target at rest (the same stopping rule as everywhere),
  and SPH's K frames from it.

The reproduced shape is compared with the target by Chamfer distance and OT (squared W2), and
by the per-particle MSE (the consistency MSE). Written: ``goal_<name>.png`` (rows = methods;
columns = target, inferred initial state, reproduced state), ``goal_<name>.gif`` (each method's
K forward frames from its initial state, the target behind) and ``goal_<name>.json``.

3D: the 2D shape stands in the x-y plane (gravity along -y) and is extruded along z, centred
in the box; figures show the x-y projection.

Command line (works without ``evaluate.py``)::

    python -m rgns.inverse.goal --ckpt A.ckpt [--ckpt B.ckpt] --text LN --out DIR
    python -m rgns.inverse.goal --ckpt A.ckpt --points circle.npy --out DIR
    python -m rgns.inverse.goal --ckpt A.ckpt --mask shape.png --out DIR
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from rgns.data.contract import WATER
from rgns.evaluation.metrics import chamfer, optimal_transport
from rgns.evaluation.plots import save_figure
from rgns.inverse.optimise import StoppingRule, optimise_initial_state
from rgns.inverse.simulators import SPHSimulator, dataset_spacing, sph_for_dataset
from rgns.models import State

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------- shapes
def _font(pixels: int) -> ImageFont.ImageFont:
    """DejaVu Sans Bold (shipped with matplotlib) at ``pixels``; PIL's default font if it is missing."""
    import matplotlib

    path = Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans-Bold.ttf"
    if path.is_file():
        return ImageFont.truetype(str(path), pixels)
    return ImageFont.load_default(size=pixels)


def render_text(text: str, pixels: int = 256) -> np.ndarray:
    """``text`` rendered in one line, cropped to its ink: a mask ``[H, W]`` bool, row 0 at the top,
    about ``pixels`` rows high for a capital letter."""
    if not text:
        raise ValueError("empty text")
    font = _font(pixels)
    left, top, right, bottom = ImageDraw.Draw(Image.new("L", (1, 1))).textbbox((0, 0), text, font=font)
    margin = 4
    image = Image.new("L", (right - left + 2 * margin, bottom - top + 2 * margin), 0)
    ImageDraw.Draw(image).text((margin - left, margin - top), text, fill=255, font=font)
    mask = np.asarray(image) >= 128
    rows, cols = np.nonzero(mask)
    return mask[rows.min(): rows.max() + 1, cols.min(): cols.max() + 1]


def load_mask(path: str | Path, invert: bool = False) -> np.ndarray:
    """An image file as a mask ``[H, W]`` bool, row 0 at the top: its alpha channel where it has
    one that is not fully opaque, else its luminance; inside = at least 128 (bright shape on a dark
    ground), or below 128 with ``invert`` (dark shape on a light ground)."""
    image = Image.open(path)
    if image.mode in ("RGBA", "LA", "PA") and np.asarray(image.getchannel("A")).min() < 255:
        values = np.asarray(image.getchannel("A"))
    else:
        values = np.asarray(image.convert("L"))
    mask = values >= 128
    return ~mask if invert else mask


def mask_to_points(mask: np.ndarray, pixel_size: float, spacing: float) -> np.ndarray:
    """Particles at ``spacing`` on a square lattice over a mask ``[H, W]`` (row 0 at the top) whose
    pixels are ``pixel_size`` wide: the cell centres ``((i + 1/2) h, (j + 1/2) h)`` that fall on a
    pixel inside. Coordinates from the mask's lower-left corner, y up.  ``-> [M, 2]``

    A filled square of side s gives ``floor(s / h)^2`` particles.
    """
    height, width = mask.shape
    counts = [int(math.floor(width * pixel_size / spacing + 1e-6)), int(math.floor(height * pixel_size / spacing + 1e-6))]
    x = (np.arange(counts[0]) + 0.5) * spacing
    y = (np.arange(counts[1]) + 0.5) * spacing
    grid = np.stack(np.meshgrid(x, y, indexing="ij"), -1).reshape(-1, 2)
    cols = np.minimum((grid[:, 0] / pixel_size).astype(int), width - 1)
    rows = np.minimum(height - 1 - (grid[:, 1] / pixel_size).astype(int), height - 1)
    return grid[mask[rows, cols]]


def extrude(points: np.ndarray, depth: float, spacing: float, centre: float) -> np.ndarray:
    """2D points ``[M, 2]`` extruded along z into ``floor(depth / h)`` layers centred on ``centre``.  ``-> [M L, 3]``"""
    layers = max(int(math.floor(depth / spacing + 1e-6)), 1)
    z = centre + (np.arange(layers) - (layers - 1) / 2) * spacing
    return np.concatenate([np.column_stack([points, np.full(len(points), zi)]) for zi in z])


def place(points: np.ndarray, bounds: np.ndarray, spacing: float, where: str = "floor") -> np.ndarray:
    """Translate a shape into the box ``[D, 2]``: ``"floor"`` centred in x (and z) and standing half a
    spacing above the floor (y = axis 1); ``"centre"`` centred in the box; ``"none"`` as given.
    Raises if the shape does not fit."""
    points = np.asarray(points, dtype=np.float64)
    if where != "none":
        lower, upper = points.min(0), points.max(0)
        shift = 0.5 * (bounds[:, 0] + bounds[:, 1]) - 0.5 * (lower + upper)
        if where == "floor":
            shift[1] = bounds[1, 0] + 0.5 * spacing - lower[1]
        elif where != "centre":
            raise ValueError(f"place must be 'floor', 'centre' or 'none', got {where!r}")
        points = points + shift
    if (points < bounds[:, 0]).any() or (points > bounds[:, 1]).any():
        raise ValueError(f"the shape (extent {points.min(0)} .. {points.max(0)}) does not fit in the box {bounds.tolist()}")
    return points


@dataclass
class GoalSpec:
    """What shape to make. Exactly one of ``text``, ``mask`` (an image file), ``points`` (``.npy`` or
    ``.txt`` ``[M, D]`` or ``[M, 2]``, in metres).

    Args:
        height: text and mask: the shape's height (m). width: mask only, its width instead (keeps the aspect).
        depth: 3D, the extrusion along z (m).
        place: ``"floor"``, ``"centre"`` or ``"none"`` (see :func:`place`).
        invert: mask: the shape is dark on a light ground.
        name: a name for the output files (default: the text, or the file's stem).
    """

    text: str | None = None
    mask: str | None = None
    points: str | None = None
    height: float = 0.3
    width: float | None = None
    depth: float = 0.1
    place: str = "floor"
    invert: bool = False
    name: str | None = None

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        return self.text if self.text else Path(self.mask or self.points).stem


def target_points(spec: GoalSpec, bounds, spacing: float, dim: int) -> np.ndarray:
    """The target particles ``[M, dim]`` of a :class:`GoalSpec` at ``spacing`` in the box ``bounds``."""
    bounds = np.asarray(bounds, dtype=np.float64)
    given = [x is not None for x in (spec.text, spec.mask, spec.points)]
    if sum(given) != 1:
        raise ValueError("give exactly one of text, mask, points")
    if spec.points is not None:
        path = Path(spec.points)
        points = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, ndmin=2)
        if points.ndim != 2 or points.shape[1] not in (2, dim):
            raise ValueError(f"{path}: points must be [M, {dim}] or [M, 2], got {points.shape}")
    else:
        mask = render_text(spec.text) if spec.text is not None else load_mask(spec.mask, spec.invert)
        pixel_size = spec.width / mask.shape[1] if spec.width is not None and spec.mask else spec.height / mask.shape[0]
        points = mask_to_points(mask, pixel_size, spacing)
        if len(points) == 0:
            raise ValueError(f"the shape {spec.label!r} has no particle at spacing {spacing}: make it larger")
    if dim == 3 and points.shape[1] == 2:
        points = extrude(points, spec.depth, spacing, 0.5 * (bounds[2, 0] + bounds[2, 1]))
    return place(points, bounds, spacing, spec.place).astype(np.float32)


def at_rest(position: torch.Tensor, history: int, particle_type: torch.Tensor | None = None) -> State:
    """The state of a shape at rest: every velocity of the history zero."""
    if particle_type is None:
        particle_type = torch.full((len(position),), WATER, dtype=torch.long)
    return State(position, torch.zeros(len(position), history, position.shape[-1]), particle_type)


# ---------------------------------------------------------------------------------------------- methods
@dataclass
class GoalRun:
    """One method's goal-conditioned result."""

    label: str
    initial: np.ndarray  # [N, D] inferred initial state's positions
    trajectory: np.ndarray  # [K + 1, N, D] forward from the initial state; trajectory[-1] reproduces the target
    seconds: float  # inverse inference (or optimisation) time
    extra: dict = field(default_factory=dict)


@torch.no_grad()
def feed_forward_goal(model, target: torch.Tensor, steps: int, label: str) -> GoalRun:
    """K inverse steps of a bidirectional simulator from the target at rest, then K forward steps."""
    state = at_rest(target, model.history)
    begin = time.perf_counter()
    for _ in range(steps):
        state = model.inverse_step(state)
    seconds = time.perf_counter() - begin
    forward = model.rollout(state, steps)
    trajectory = torch.cat([state.position.unsqueeze(0), forward]).numpy()
    return GoalRun(label, state.position.numpy(), trajectory, seconds, dict(status="feed_forward"))


def sph_goal(target: torch.Tensor, steps: int, metadata: dict, rule: StoppingRule, label: str = "SPH + Adam",
             substeps: int = 25, solver=None, **options) -> GoalRun:
    """The optimisation baseline: Adam through the differentiable SPH from the target at rest
    (the goal includes being at rest: the final velocity is asked to be zero)."""
    solver = solver or sph_for_dataset(metadata, capacity=len(target), substeps=substeps)
    simulator = SPHSimulator(solver)
    result = optimise_initial_state(simulator, target, steps, target_velocity=torch.zeros_like(target), rule=rule,
                                    **options)
    trajectory = simulator.trajectory(result.initial_position, result.initial_velocity, steps).numpy()
    return GoalRun(label, result.initial_position.numpy(), trajectory, result.seconds, result.summary())


def shape_metrics(reproduced: np.ndarray, target: np.ndarray) -> dict:
    x, y = torch.as_tensor(reproduced, dtype=torch.float64), torch.as_tensor(target, dtype=torch.float64)
    if not torch.isfinite(x).all():
        return dict(chamfer=None, ot=None, consistency_mse=None)
    return dict(chamfer=chamfer(x, y), ot=optimal_transport(x, y), consistency_mse=float((x - y).pow(2).mean()))


# ---------------------------------------------------------------------------------------------- outputs
def _scatter(ax, points: np.ndarray, bounds: np.ndarray, colour, size: float, alpha: float = 1.0) -> None:
    ax.scatter(points[:, 0], points[:, 1], s=size, color=colour, alpha=alpha, linewidths=0)
    ax.set_xlim(*bounds[0])
    ax.set_ylim(*bounds[1])
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def goal_figure(target: np.ndarray, runs: list[GoalRun], bounds, path: Path, title: str) -> None:
    """Rows = methods; columns = target, inferred initial state, reproduced state (x-y plane)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bounds = np.asarray(bounds)
    size = max(0.5, min(6.0, 4000 / max(len(target), 1)))
    fig, axes = plt.subplots(len(runs), 3, figsize=(9, 3 * len(runs)), squeeze=False)
    for row, run in zip(axes, runs):
        finite = np.isfinite(run.trajectory[-1]).all()
        _scatter(row[0], target, bounds, "tab:blue", size)
        _scatter(row[1], run.initial, bounds, "tab:orange", size)
        _scatter(row[2], target, bounds, "lightgrey", size)
        if finite:
            _scatter(row[2], run.trajectory[-1], bounds, "tab:green", size)
        row[0].set_ylabel(run.label, fontsize=11)
        metrics = run.extra.get("metrics", {})
        chamfer_value = metrics.get("chamfer")
        row[2].set_title("reproduced" + (f" (Chamfer {chamfer_value:.2e})" if chamfer_value is not None else
                                         " (non-finite)"), fontsize=9)
        status = run.extra.get("status", "feed_forward")
        note = "" if status == "feed_forward" else f", {status}"
        row[1].set_title(f"inferred initial state ({run.seconds:.2f} s{note})", fontsize=9)
        row[0].set_title("target", fontsize=9)
    fig.suptitle(title)
    save_figure(fig, path)


def goal_animation(target: np.ndarray, runs: list[GoalRun], bounds, path: Path, fps: int = 10,
                   max_frames: int = 60) -> None:
    """One panel per method: its K forward frames from the inferred initial state, the target behind."""
    import imageio.v2 as imageio
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bounds = np.asarray(bounds)
    size = max(0.5, min(6.0, 4000 / max(len(target), 1)))
    length = max(len(r.trajectory) for r in runs)
    frames_at = np.unique(np.linspace(0, length - 1, min(length, max_frames)).round().astype(int))
    images = []
    for t in frames_at:
        fig, axes = plt.subplots(1, len(runs), figsize=(3.2 * len(runs), 3.4), squeeze=False)
        for ax, run in zip(axes[0], runs):
            frame = run.trajectory[min(t, len(run.trajectory) - 1)]
            _scatter(ax, target, bounds, "lightgrey", size)
            if np.isfinite(frame).all():
                _scatter(ax, frame, bounds, "tab:blue", size)
            ax.set_title(f"{run.label}: frame {min(t, len(run.trajectory) - 1)}", fontsize=9)
        fig.tight_layout()
        fig.canvas.draw()
        images.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        plt.close(fig)
    imageio.mimsave(path, images, duration=1000 / fps, loop=0)


# ---------------------------------------------------------------------------------------------- entry points
def run_goal(models: dict, metadata: dict, spec: GoalSpec, out_dir: str | Path, steps: int = 20,
             optimiser: dict | None = None, frame: np.ndarray | None = None, fps: int = 10) -> dict:
    """The goal-conditioned task for several methods on one dataset; writes figure, GIF and JSON.

    Args:
        models: ``{label: Simulator}``; the bidirectional ones run feed-forward inverse inference.
        metadata: the dataset's ``metadata.json`` (box, spacing or ``frame``, frame time, gravity).
        spec: the :class:`GoalSpec`.
        out_dir: where ``goal_<name>.{png,gif,json}`` go.
        steps: K.
        optimiser: the SPH + Adam baseline's settings, ``None`` to skip it:
            ``{"rule": {StoppingRule fields}, "lr": ..., "clip": ..., "schedule": ..., "substeps": ...}``.
        frame: ``[N, D]`` a dataset frame to measure the spacing from, when the metadata has none.

    Returns the JSON written: target size and spacing, and per method its metrics (Chamfer, OT,
    consistency MSE), seconds and status.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    spacing = dataset_spacing(metadata, frame)
    dim = int(metadata["dim"])
    target = torch.as_tensor(target_points(spec, metadata["bounds"], spacing, dim))
    log.info("goal %r: %d particles at spacing %g", spec.label, len(target), spacing)
    runs = []
    for label, model in models.items():
        if not model.bidirectional:
            log.info("%s: forward-only, skipped (no inverse)", label)
            continue
        runs.append(feed_forward_goal(model, target, steps, label))
    if optimiser is not None and dim in (2, 3):
        options = dict(optimiser)
        rule = StoppingRule(**options.pop("rule", {}))
        runs.append(sph_goal(target, steps, metadata, rule, **options))
    target_np = target.numpy()
    for run in runs:
        run.extra["metrics"] = shape_metrics(run.trajectory[-1], target_np)
    name = "".join(c if c.isalnum() else "_" for c in spec.label)
    title = f"goal {spec.label!r}: {len(target)} particles, K = {steps}"
    goal_figure(target_np, runs, metadata["bounds"], out_dir / f"goal_{name}.png", title)
    goal_animation(target_np, runs, metadata["bounds"], out_dir / f"goal_{name}.gif", fps=fps)
    results = dict(goal=vars(spec), particles=len(target), spacing=spacing, steps=steps, dim=dim,
                   state_at_rest="velocity history all zero",
                   methods={r.label: dict(r.extra, seconds=r.seconds) for r in runs},
                   files=[f"goal_{name}.png", f"goal_{name}.gif", f"goal_{name}.json"])
    (out_dir / f"goal_{name}.json").write_text(json.dumps(results, indent=2) + "\n")
    return results


class GoalShaping:
    """:func:`run_goal` as an ``evaluate.py`` task (``task(methods, dataset) -> (results, examples)``),
    e.g. ``task=goal goal.text=LN``; files go to ``<out_dir>/goal_<dataset>/``.

    Args: ``out_dir`` (the run folder), ``steps`` (K), ``optimiser`` (as :func:`run_goal`, ``None``
    to skip SPH + Adam), and the :class:`GoalSpec` fields (``text``, ``mask``, ``points``, ``height``, ...).
    """

    name = "goal"

    def __init__(self, out_dir: str, steps: int = 20, optimiser: dict | None = None, **shape):
        if steps < 1:
            raise ValueError(f"goal.steps={steps}: K, the inverse steps from the target, must be at least 1")
        self.out_dir, self.steps, self.optimiser = out_dir, steps, optimiser
        self.spec = GoalSpec(**shape)

    def __call__(self, methods, dataset) -> tuple[dict, dict]:
        models = {m.label: m.model for m in methods}
        frame = dataset.trajectories[0][0][0].cpu().numpy()
        optimiser = None if self.optimiser is None else json.loads(json.dumps(dict(self.optimiser)))
        results = run_goal(models, dataset.metadata, self.spec, Path(self.out_dir) / f"goal_{dataset.name}",
                           self.steps, optimiser, frame)
        return results, {}


def _label(model, extras: dict, path: str) -> str:
    names = {"RGNS": "R-GNS", "SepGNS": "Sep-GNS", "GNS": "GNS"}
    return f"{names.get(type(model).__name__, type(model).__name__)} ({Path(path).parent.parent.name})"


def main(argv: list[str] | None = None) -> dict:
    from rgns.data.contract import check_dataset, open_split
    from rgns.evaluation.methods import check_fits
    from rgns.training.module import load_simulator

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", action="append", required=True, help="a checkpoint (repeat for several)")
    shape = parser.add_mutually_exclusive_group(required=True)
    shape.add_argument("--text")
    shape.add_argument("--mask", help="an image file (bright shape on dark, or --invert)")
    shape.add_argument("--points", help="a .npy or .txt [M, D] point file, in metres")
    parser.add_argument("--invert", action="store_true")
    parser.add_argument("--height", type=float, default=0.3, help="text/mask height (m)")
    parser.add_argument("--depth", type=float, default=0.1, help="3D extrusion along z (m)")
    parser.add_argument("--place", default="floor", choices=["floor", "centre", "none"])
    parser.add_argument("--steps", type=int, default=20, help="K")
    parser.add_argument("--data-root", help="the dataset (default: the first checkpoint's)")
    parser.add_argument("--no-optimiser", action="store_true", help="skip the SPH + Adam baseline")
    parser.add_argument("--iterations", type=int, default=30, help="SPH + Adam iteration cap")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    if args.steps < 1 or args.iterations < 1:
        parser.error(f"--steps {args.steps} and --iterations {args.iterations}: each must be at least 1")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)

    models, root = {}, args.data_root
    for path in args.ckpt:
        model, extras = load_simulator(path)
        label = _label(model, extras, path)
        models[label if label not in models else f"{label} {Path(path).name}"] = model  # two of one run stay apart
        root = root or extras["data_root"]
    if root is None:
        raise SystemExit("the checkpoint does not name its dataset: pass --data-root")
    contents = check_dataset(root, splits=("train",))
    for path, model in zip(args.ckpt, models.values()):
        check_fits(model, path, contents.metadata, contents.particle_types["train"], str(Path(root) / "train.h5"))
    metadata = contents.metadata
    with open_split(root, "train") as data:
        frame = data[0][0][0]
    spec = GoalSpec(text=args.text, mask=args.mask, points=args.points, height=args.height, depth=args.depth,
                    place=args.place, invert=args.invert)
    optimiser = None if args.no_optimiser else dict(rule=dict(max_iterations=args.iterations))
    results = run_goal(models, metadata, spec, args.out, args.steps, optimiser, frame)
    for label, row in results["methods"].items():
        m = row["metrics"]
        print(f"{label:32s} chamfer={m['chamfer']} ot={m['ot']} consistency_mse={m['consistency_mse']} "
              f"seconds={row['seconds']:.3f} status={row.get('status')}")
    print(f"wrote {', '.join(str(Path(args.out) / f) for f in results['files'])}")
    return results


if __name__ == "__main__":
    main()
