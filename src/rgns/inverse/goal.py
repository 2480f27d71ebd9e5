"""Goal-conditioned shaping: steer a fluid into a target shape (the paper's letters "L" and "N").

A target is given as text, an image mask or a point file, and becomes particles at the dataset's
spacing, placed in the box with a velocity: by default **mid-air and at rest at frame K**
(``place="air"``: centred in x (and z), its bottom ``lift`` metres above the floor; every slot of
the velocity history zero), the top of a flight, so that earlier the water was lower and rising
and an inverse model has to find that past. Any placement may be given a uniform velocity
``velocity`` (m/s): every slot of the velocity history is then ``velocity * dt``, the per-frame
displacement that :class:`rgns.models.State` holds. Per horizon K (several: ``steps``), and per method:

- a bidirectional learned simulator (R-GNS, Sep-GNS): K inverse steps from the target to an
  inferred initial state, then K forward steps from it to the model's reproduction;
- optimisation baselines (``optimisers``: ``sph``, differentiable SPH + Adam; ``mpm``, MLS-MPM in
  torch autograd + Adam; :func:`rgns.inverse.tasks._optimiser_simulator`): Adam from the target
  (with its velocity) to reach the target positions and velocity at frame K, under one stopping
  rule, and the optimiser's own simulator's K frames from the initial state it found;
- **do nothing**: the target itself, with its velocity, as the initial state: what the shape
  becomes if nobody plans.

**The physics check.** Every method's initial state (positions, and the velocity its newest
history slot implies, divided by the frame time into m/s) is also run K frames forward by the
dataset's own ground-truth solver (the scene the metadata's generator names, rebuilt by
:func:`rgns.evaluation.references.rebuild_scene`: MLS-MPM for the water scenes, SPH for water3d),
and the solver's final frame is compared with the target. Particles outside the box are first
clamped onto it (the solver keeps none outside); the fraction clamped is reported. Each initial
state is also checked for plausibility (:func:`plausibility`): the fraction inside the box, the
fractions whose nearest neighbour is closer than ``OVERLAP`` (0.5) spacings (overlaps) or farther
than ``ISOLATED`` (2) spacings (isolated particles, spray or holes), and its largest speed against
the largest in the training data. A dataset without a generator gets no physics check (a sentence says why).

The reproductions are compared with the target by Chamfer distance and OT (squared W2), and by
the per-particle MSE (the consistency MSE). Written per K: ``goal_<name>_K<K>.png`` (rows =
methods; columns = target, inferred initial state, reproduced by the model, reproduced by the
solver) and ``goal_<name>_K<K>.gif`` (the solver's K frames from each method's initial state, the
target behind; the model's where there is no solver), and ``goal_<name>.json``.

3D: the 2D shape stands in the x-y plane (gravity along -y) and is extruded along z, centred
in the box; the figure has two rows per method, the scene seen from the front (x against the axis
gravity pulls along) and from above (x-z), and the animation two panels per method, one of each
view; every title names its view. Several texts (``goal.text=[L,N]``, ``--text L N``) are
separate targets, run one after the other, each into its own files (``goal_L_K40.png``, ...).

Command line (works without ``evaluate.py``)::

    python -m rgns.inverse.goal --ckpt A.ckpt [--ckpt B.ckpt] --text LN --steps 20 40 100 --out DIR
    python -m rgns.inverse.goal --ckpt A.ckpt --text L N --steps 40 --out DIR   # two targets, "L" and "N"
    python -m rgns.inverse.goal --ckpt A.ckpt --points circle.npy --place centre --velocity 0 1 --out DIR
    python -m rgns.inverse.goal --ckpt A.ckpt --mask shape.png --out DIR
"""
from __future__ import annotations

import argparse
import io
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from rgns.data.contract import KINEMATIC, WATER
from rgns.evaluation.metrics import chamfer, optimal_transport
from rgns.evaluation.plots import save_figure, up_axis, view_name, views, write_whole
from rgns.inverse.optimise import StoppingRule, optimise_initial_state
from rgns.inverse.simulators import dataset_spacing
from rgns.inverse.tasks import _optimiser_simulator, _warm_up, add_out_arguments, chosen_optimisers, refuse_earlier_out
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


def place(points: np.ndarray, bounds: np.ndarray, spacing: float, where: str = "air", lift: float = 0.1) -> np.ndarray:
    """Translate a shape into the box ``[D, 2]``: ``"air"`` centred in x (and z), its bottom ``lift``
    above the floor (y = axis 1); ``"floor"`` centred in x (and z) and standing half a spacing above
    the floor; ``"centre"`` centred in the box; ``"none"`` as given. Raises if the shape does not fit."""
    points = np.asarray(points, dtype=np.float64)
    if where != "none":
        lower, upper = points.min(0), points.max(0)
        shift = 0.5 * (bounds[:, 0] + bounds[:, 1]) - 0.5 * (lower + upper)
        if where == "floor":
            shift[1] = bounds[1, 0] + 0.5 * spacing - lower[1]
        elif where == "air":
            shift[1] = bounds[1, 0] + lift - lower[1]
        elif where != "centre":
            raise ValueError(f"place must be 'air', 'floor', 'centre' or 'none', got {where!r}")
        points = points + shift
    if (points < bounds[:, 0]).any() or (points > bounds[:, 1]).any():
        raise ValueError(f"the shape (extent {points.min(0)} .. {points.max(0)}) does not fit in the box {bounds.tolist()}")
    return points


@dataclass
class GoalSpec:
    """What shape to make, where, and how fast it moves at frame K. Exactly one of ``text``,
    ``mask`` (an image file), ``points`` (``.npy`` or ``.txt`` ``[M, D]`` or ``[M, 2]``, in metres).

    Args:
        height: text and mask: the shape's height (m). width: mask only, its width instead (keeps the aspect).
        depth: 3D, the extrusion along z (m).
        place: ``"air"``, ``"floor"``, ``"centre"`` or ``"none"`` (see :func:`place`).
        lift: ``"air"``: the height of the shape's bottom above the floor (m).
        velocity: the target's uniform velocity at frame K (m/s, ``[D]``, or ``[2]`` in 3D: z is 0);
            ``None``: at rest.
        invert: mask: the shape is dark on a light ground.
        name: a name for the output files (default: the text, or the file's stem).
    """

    text: str | None = None
    mask: str | None = None
    points: str | None = None
    height: float = 0.3
    width: float | None = None
    depth: float = 0.1
    place: str = "air"
    lift: float = 0.1
    velocity: list[float] | None = None
    invert: bool = False
    name: str | None = None

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        return self.text if self.text else Path(self.mask or self.points).stem

    def target_velocity(self, dim: int) -> np.ndarray:
        """The target's velocity ``[dim]`` in m/s (zero at rest)."""
        velocity = np.zeros(dim) if self.velocity is None else np.asarray(self.velocity, dtype=np.float64)
        if velocity.shape == (2,) and dim == 3:
            velocity = np.append(velocity, 0.0)
        if velocity.shape != (dim,):
            raise ValueError(f"goal velocity {self.velocity}: give {dim} components (m/s), or null for at rest")
        return velocity


def target_points(spec: GoalSpec, bounds, spacing: float, dim: int) -> np.ndarray:
    """The target particles ``[M, dim]`` of a :class:`GoalSpec` at ``spacing`` in the box ``bounds``."""
    bounds = np.asarray(bounds, dtype=np.float64)
    given = [x is not None for x in (spec.text, spec.mask, spec.points)]
    if sum(given) != 1:
        raise ValueError("give exactly one of text, mask, points")
    if spec.points is not None:
        path = Path(spec.points)
        try:  # np.load refuses pickled objects (allow_pickle=False): a points file is numbers only
            points = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, ndmin=2)
        except (OSError, ValueError) as err:
            raise ValueError(f"{path}: not a readable points file ({type(err).__name__}: {err})") from None
        if points.ndim != 2 or points.shape[1] not in (2, dim) or len(points) == 0:
            raise ValueError(f"{path}: points must be [M, {dim}] or [M, 2] with M >= 1, got {points.shape}")
        if not np.isfinite(points).all():
            row = int(np.nonzero(~np.isfinite(points).all(axis=1))[0][0])
            raise ValueError(f"{path}: points hold NaN or Inf (first in row {row}); a target is finite positions")
    else:
        mask = render_text(spec.text) if spec.text is not None else load_mask(spec.mask, spec.invert)
        pixel_size = spec.width / mask.shape[1] if spec.width is not None and spec.mask else spec.height / mask.shape[0]
        points = mask_to_points(mask, pixel_size, spacing)
        if len(points) == 0:
            raise ValueError(f"the shape {spec.label!r} has no particle at spacing {spacing}: make it larger")
    if dim == 3 and points.shape[1] == 2:
        points = extrude(points, spec.depth, spacing, 0.5 * (bounds[2, 0] + bounds[2, 1]))
    return place(points, bounds, spacing, spec.place, spec.lift).astype(np.float32)


def target_state(position: torch.Tensor, history: int, velocity: torch.Tensor | None = None,
                 particle_type: torch.Tensor | None = None) -> State:
    """The target as a model's state: every slot of the velocity history is ``velocity`` ``[D]``,
    a displacement per frame (m/s times the frame time, as :class:`State` holds velocities);
    zero (at rest) when ``None``.  ``position [N, D] -> State(velocity_history [N, k, D])``"""
    if particle_type is None:
        particle_type = torch.full((len(position),), WATER, dtype=torch.long)
    velocity = torch.zeros(position.shape[-1]) if velocity is None else torch.as_tensor(velocity)
    velocity_history = velocity.to(position).expand(len(position), history, position.shape[-1]).clone()  # [N, k, D]
    return State(position, velocity_history, particle_type)


# ---------------------------------------------------------------------------------------------- the physics check
OVERLAP = 0.5  # a nearest neighbour closer than this many spacings: two particles on top of each other
ISOLATED = 2.0  # farther than this many: a particle with no neighbour at the lattice distance (spray, a hole)


def plausibility(position: np.ndarray, velocity: np.ndarray, bounds, spacing: float, dt: float,
                 max_speed: float | None = None) -> dict:
    """How physical an initial state ``position [N, D]`` with per-frame ``velocity [N, D]`` looks:
    the fraction inside the box ``bounds``, the fractions whose nearest neighbour is closer than
    ``OVERLAP`` or farther than ``ISOLATED`` spacings, the largest speed (m/s) against ``max_speed``
    (the training data's), the mean velocity (m/s), and ``flags``: a sentence per check that fails."""
    from scipy.spatial import cKDTree

    position, bounds = np.asarray(position, dtype=np.float64), np.asarray(bounds, dtype=np.float64)
    if not (np.isfinite(position).all() and np.isfinite(velocity).all()):
        return dict(finite=False, flags=["not finite"])
    inside = float(((position >= bounds[:, 0]) & (position <= bounds[:, 1])).all(1).mean())
    distance, _ = cKDTree(position).query(position, k=2)
    nearest = distance[:, 1] / spacing  # [N], in spacings
    speed = float(np.linalg.norm(velocity, axis=1).max()) / dt
    result = dict(finite=True, inside_box=inside, overlapping=float((nearest < OVERLAP).mean()),
                  isolated=float((nearest > ISOLATED).mean()), nearest_median=float(np.median(nearest)),
                  max_speed=speed, train_max_speed=max_speed, mean_velocity=(np.mean(velocity, 0) / dt).tolist())
    flags = []
    if inside < 1:
        flags.append(f"{1 - inside:.1%} outside the box")
    if result["overlapping"] > 0:
        flags.append(f"{result['overlapping']:.1%} overlapping (< {OVERLAP} spacing)")
    if result["isolated"] > 0:
        flags.append(f"{result['isolated']:.1%} isolated (> {ISOLATED} spacings)")
    if max_speed is not None and speed > max_speed:
        flags.append(f"max speed {speed:.2f} m/s over the training data's {max_speed:.2f}")
    return dict(result, flags=flags)


def data_max_speed(trajectories, dt: float) -> float:
    """The largest speed (m/s) of the moving particles in ``[(position [T, N, D], particle_type [N])]``."""
    speeds = [np.linalg.norm(np.diff(np.asarray(p)[:, np.asarray(t) != KINEMATIC], axis=0), axis=-1).max()
              for p, t in trajectories]
    return float(max(speeds)) / dt


class GroundTruthSolver:
    """The dataset's own solver (:func:`rgns.evaluation.references.rebuild_scene`), run K frames from
    an initial state in the box; positions outside it are clamped onto its walls first.

    Args:
        scene: the rebuilt scene (its ``solver``, ``bounds``, ``dt``, ``material``).
    """

    def __init__(self, scene):
        self.scene = scene
        self.label = type(scene.solver).__name__.removesuffix("Solver")
        self._warm = False

    @classmethod
    def for_dataset(cls, metadata: dict, particles: int) -> tuple["GroundTruthSolver | None", str | None]:
        """The solver of a generated dataset, with room for ``particles``; or ``None`` and the reason."""
        from rgns.evaluation.references import rebuild_scene

        capacity = int(((metadata.get("generator") or {}).get("params") or {}).get("capacity", 0))
        try:
            return cls(rebuild_scene(metadata, capacity=max(capacity, particles))), None
        except Exception as error:  # noqa: BLE001 - no physics check is reported, not raised
            return None, f"No physics check: {error}."

    def run(self, position: np.ndarray, velocity: np.ndarray, steps: int) -> tuple[np.ndarray | None, dict]:
        """Frames ``0 .. steps`` ``[K + 1, N, D]`` from ``position`` with per-frame ``velocity``
        ``[N, D]``, and what happened: ``clamped`` (the fraction moved into the box), ``seconds``,
        ``error`` (the solver failed or the state is not finite: no frames)."""
        from rgns.physics import runtime

        if not (np.isfinite(position).all() and np.isfinite(velocity).all()):
            return None, dict(error="the initial state is not finite")
        inside = np.clip(position, self.scene.lower, self.scene.upper)
        clamped = float((inside != position).any(1).mean())
        material = np.full(len(inside), self.scene.material, np.int64)
        velocity = np.asarray(velocity, dtype=np.float64) / self.scene.dt  # per frame -> m/s
        runtime.ensure_taichi()
        if not self._warm:  # Taichi compiles its kernels on the first call: not timed
            self.scene.solver.rollout(inside, velocity, material, 2)
            self._warm = True
        begin = time.perf_counter()
        try:
            frames = self.scene.solver.rollout(inside, velocity, material, steps + 1)
        except Exception as error:  # noqa: BLE001 - a failed run is a result
            return None, dict(clamped=clamped, error=f"{type(error).__name__}: {error}")
        return frames, dict(clamped=clamped, seconds=time.perf_counter() - begin)


# ---------------------------------------------------------------------------------------------- methods
@dataclass
class GoalRun:
    """One method's goal-conditioned result at one K."""

    label: str
    initial: np.ndarray  # [N, D] the initial state's positions
    velocity: np.ndarray  # [N, D] its newest velocity, per frame
    trajectory: np.ndarray | None  # [K + 1, N, D] its own simulator from the initial state (None: no model)
    seconds: float  # inverse inference (or optimisation) time
    extra: dict = field(default_factory=dict)
    solver: np.ndarray | None = None  # [K + 1, N, D] the ground-truth solver from the initial state


@torch.no_grad()
def feed_forward_goal(model, target: State, steps: int, label: str) -> GoalRun:
    """K inverse steps of a bidirectional simulator from the target state, then K forward steps."""
    state = target
    begin = time.perf_counter()
    for _ in range(steps):
        state = model.inverse_step(state)
    seconds = time.perf_counter() - begin
    forward = model.rollout(state, steps)
    trajectory = torch.cat([state.position.unsqueeze(0), forward]).numpy()
    return GoalRun(label, state.position.numpy(), state.velocity_history[:, -1].numpy(), trajectory, seconds,
                   dict(status="feed_forward"))


def optimiser_goal(kind: str, options: dict, metadata: dict, target: torch.Tensor, velocity: torch.Tensor,
                   steps: int, rule: StoppingRule) -> GoalRun:
    """An optimisation baseline (``kind`` ``sph`` or ``mpm``, :func:`rgns.inverse.tasks._optimiser_simulator`):
    Adam from the target with its velocity ``[D]`` (per frame), asked to reach the target positions
    and that velocity at frame K; its own simulator's K frames from the initial state it found.
    ``options``: ``lr``, ``velocity_lr``, ``clip``, ``schedule``, ``substeps`` (sph), ``solver`` (mpm),
    and ``rule`` (this optimiser's changes to the stopping rule, e.g. a lower ``max_iterations``)."""
    particle_type = torch.full((len(target),), WATER, dtype=torch.long)
    simulator, label = _optimiser_simulator(kind, options, metadata, {}, len(target), particle_type)
    target_velocity = velocity.to(target).expand_as(target).clone()  # [N, D]
    _warm_up(simulator, target, target_velocity)
    rule = StoppingRule(**{**vars(rule), **options.get("rule", {})})
    solve = {k: options[k] for k in ("lr", "velocity_lr", "clip", "schedule") if k in options}
    result = optimise_initial_state(simulator, target, steps, init_position=target, init_velocity=target_velocity,
                                    target_velocity=target_velocity, rule=rule, **solve)
    trajectory = simulator.trajectory(result.initial_position, result.initial_velocity, steps).numpy()
    return GoalRun(label, result.initial_position.numpy(), result.initial_velocity.detach().numpy(), trajectory,
                   result.seconds, result.summary())


def do_nothing(target: torch.Tensor, velocity: torch.Tensor) -> GoalRun:
    """The target itself, with its velocity ``[D]`` (per frame), as the initial state: no planning."""
    return GoalRun("do nothing", target.numpy(), velocity.to(target).expand_as(target).numpy().copy(), None, 0.0,
                   dict(status="no planning"))


def shape_metrics(reproduced: np.ndarray | None, target: np.ndarray) -> dict | None:
    """Chamfer, OT and the per-particle MSE of a reproduced shape ``[N, D]`` against the target;
    ``None`` where there is none, ``None`` values where it is not finite."""
    if reproduced is None:
        return None
    x, y = torch.as_tensor(reproduced, dtype=torch.float64), torch.as_tensor(target, dtype=torch.float64)
    if not torch.isfinite(x).all():
        return dict(chamfer=None, ot=None, consistency_mse=None)
    return dict(chamfer=chamfer(x, y), ot=optimal_transport(x, y), consistency_mse=float((x - y).pow(2).mean()))


# ---------------------------------------------------------------------------------------------- outputs
def _scatter(ax, points: np.ndarray, bounds: np.ndarray, colour, size: float, view=(0, 1, "")) -> None:
    """Particles ``[N, D]`` seen along ``view`` ``(horizontal axis, vertical axis, name)``, in the box."""
    across, up, _ = view
    ax.scatter(points[:, across], points[:, up], s=size, color=colour, linewidths=0)
    ax.set_xlim(*bounds[across])
    ax.set_ylim(*bounds[up])
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def _chamfer_title(name: str, metrics: dict | None) -> str:
    if metrics is None:
        return f"{name}: none"
    value = metrics.get("chamfer")
    return f"{name} (Chamfer {value:.2e})" if value is not None else f"{name} (non-finite)"


def goal_figure(target: np.ndarray, runs: list[GoalRun], bounds, path: Path, title: str, up: int = 1) -> None:
    """Rows = methods; columns = target, inferred initial state, reproduced by the model, reproduced
    by the solver. 2D: the x-y plane. 3D: two rows per method, seen from the front (x against the
    ``up`` axis) and from above (x-z), the view named in each title, the target in grey under the
    method's particles in every panel but the target's own."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bounds = np.asarray(bounds)
    projections = views(len(bounds), up)
    size = max(0.5, min(6.0, 4000 / max(len(target), 1)))
    rows = len(runs) * len(projections)
    fig, axes = plt.subplots(rows, 4, figsize=(12, 3 * rows), squeeze=False)
    for m, run in enumerate(runs):
        status = run.extra.get("status", "feed_forward")
        note = "" if status in ("feed_forward", "no planning") else f", {status}"
        flags = run.extra.get("plausibility", {}).get("flags")
        titles = ["target", f"initial state ({run.seconds:.2f} s{note})" + ("\n" + "; ".join(flags) if flags else ""),
                  _chamfer_title("by the model", run.extra.get("model")),
                  _chamfer_title("by the solver", run.extra.get("solver"))]
        for v, view in enumerate(projections):
            row = axes[m * len(projections) + v]
            _scatter(row[0], target, bounds, "tab:blue", size, view)
            if view[2]:  # 3D: where the initial state stands against the target
                _scatter(row[1], target, bounds, "lightgrey", size, view)
            _scatter(row[1], run.initial, bounds, "tab:orange", size, view)
            for ax, frames in ((row[2], run.trajectory), (row[3], run.solver)):
                _scatter(ax, target, bounds, "lightgrey", size, view)
                if frames is not None and np.isfinite(frames[-1]).all():
                    _scatter(ax, frames[-1], bounds, "tab:green", size, view)
            row[0].set_ylabel(run.label + (f"\n{view_name(view)}" if view[2] else ""), fontsize=11)
            for ax, text in zip(row, titles):
                seen = f"\n{view_name(view)}" if view[2] else ""
                ax.set_title(text + seen, fontsize=7 if (flags and ax is row[1]) or view[2] else 9)
    fig.suptitle(title)
    save_figure(fig, path)


def goal_animation(target: np.ndarray, runs: list[GoalRun], bounds, path: Path, fps: int = 10,
                   max_frames: int = 60, up: int = 1) -> None:
    """One panel per method: the solver's K frames from its initial state (the model's where there
    is no solver run), the target behind. 3D: two panels per method, one above the other, seen
    from the front (x against the ``up`` axis) and from above (x-z); at most ``PANELS_PER_ROW``
    methods a row."""
    import imageio.v2 as imageio
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rgns.evaluation.plots import PANELS_PER_ROW

    bounds = np.asarray(bounds)
    projections = views(len(bounds), up)
    size = max(0.5, min(6.0, 4000 / max(len(target), 1)))
    shown = [(run, run.solver if run.solver is not None else run.trajectory,
              "solver" if run.solver is not None else "model") for run in runs]
    shown = [(run, frames, by) for run, frames, by in shown if frames is not None]
    if not shown:
        return
    columns = len(shown) if len(projections) == 1 else min(len(shown), PANELS_PER_ROW)  # 2D: one row, as always
    rows = len(projections) * math.ceil(len(shown) / columns)
    length = max(len(frames) for _, frames, _ in shown)
    frames_at = np.unique(np.linspace(0, length - 1, min(length, max_frames)).round().astype(int))
    images = []
    for t in frames_at:
        fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 3.4 * rows), dpi=80, squeeze=False)
        for ax in axes.flat[len(shown) * len(projections):]:
            ax.set_axis_off()
        for i, (run, frames, by) in enumerate(shown):
            frame = frames[min(t, len(frames) - 1)]
            block, column = divmod(i, columns)
            for v, view in enumerate(projections):
                ax = axes[block * len(projections) + v, column]
                _scatter(ax, target, bounds, "lightgrey", size, view)
                if np.isfinite(frame).all():
                    _scatter(ax, frame, bounds, "tab:blue", size, view)
                seen = f"\n{view_name(view)}" if view[2] else ""
                ax.set_title(f"{run.label} ({by}): frame {min(t, len(frames) - 1)}{seen}", fontsize=8)
        fig.tight_layout()
        fig.canvas.draw()
        images.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        plt.close(fig)
    buffer = io.BytesIO()
    imageio.mimsave(buffer, images, format="GIF", duration=1000 / fps, loop=0)
    write_whole(path, buffer.getvalue())


# ---------------------------------------------------------------------------------------------- entry points
def _horizons(steps) -> list[int]:
    horizons = [steps] if isinstance(steps, int) else list(steps)
    if not horizons or min(horizons) < 1:
        shown = steps if isinstance(steps, int) else horizons
        raise ValueError(f"goal.steps={shown}: K, the inverse steps from the target, must be at least 1")
    return sorted(set(horizons))


def file_name(spec: GoalSpec) -> str:
    """What a target's files are called after: its label, each character that is not a letter or
    digit as ``_`` (``goal_<name>_K<K>.png``)."""
    return "".join(c if c.isalnum() else "_" for c in spec.label)


def run_goal(models: dict, metadata: dict, spec: GoalSpec, out_dir: str | Path, steps=(20, 40, 100),
             optimisers: dict | None = None, rule: dict | None = None, frame: np.ndarray | None = None,
             max_speed: float | None = None, physics: bool = True, fps: int = 10) -> dict:
    """The goal-conditioned task for several methods on one dataset; writes figures, GIFs and JSON.

    Args:
        models: ``{label: Simulator}``; the bidirectional ones run feed-forward inverse inference.
        metadata: the dataset's ``metadata.json`` (box, spacing or ``frame``, frame time, gravity;
            its ``generator`` for the physics check).
        spec: the :class:`GoalSpec`.
        out_dir: where ``goal_<name>_K<K>.{png,gif}`` and ``goal_<name>.json`` go.
        steps: K, one or several.
        optimisers: ``{kind: options}``, kind ``sph`` or ``mpm`` (see :func:`optimiser_goal`;
            ``horizons``: only these K); ``None``: none; a kind set to ``None``: left out.
        rule: the :class:`StoppingRule` fields every optimiser shares.
        frame: ``[N, D]`` a dataset frame to measure the spacing from, when the metadata has none.
        max_speed: the training data's largest speed (m/s), for the plausibility check (``None``: not checked).
        physics: run each initial state forward by the dataset's own solver (and the do-nothing baseline).

    Returns the JSON written: the target (size, spacing, velocity), the physics check's solver (or
    why there is none), and per K and method: ``model`` and ``solver`` metrics (Chamfer, OT,
    consistency MSE) of the two reproductions, ``plausibility``, ``seconds``, ``status``.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    horizons = _horizons(steps)
    spacing = dataset_spacing(metadata, frame)
    dim, dt, bounds = int(metadata["dim"]), float(metadata["dt"]), metadata["bounds"]
    target = torch.as_tensor(target_points(spec, bounds, spacing, dim))
    velocity_si = spec.target_velocity(dim)
    velocity = torch.as_tensor(velocity_si * dt, dtype=torch.float32)  # per frame, as State holds it
    log.info("goal %r: %d particles at spacing %g, velocity %s m/s", spec.label, len(target), spacing, velocity_si)
    solver, note = GroundTruthSolver.for_dataset(metadata, len(target)) if physics else (None, "No physics check (physics=false).")
    stopping = StoppingRule(**(rule or {}))
    name = file_name(spec)
    up = up_axis(metadata)  # the figures' vertical axis: the one gravity pulls along
    target_np, files, per_k = target.numpy(), [], {}
    for K in horizons:
        runs = []
        for label, model in models.items():
            if not model.bidirectional:
                log.info("%s: forward-only, skipped (no inverse)", label)
                continue
            runs.append(feed_forward_goal(model, target_state(target, model.history, velocity), K, label))
        for kind, options in chosen_optimisers(optimisers).items():
            if "horizons" in options and K not in options["horizons"]:
                continue
            runs.append(optimiser_goal(kind, options, metadata, target, velocity, K, stopping))
        if solver is not None:
            runs.append(do_nothing(target, velocity))
        for run in runs:
            run.extra["model"] = shape_metrics(None if run.trajectory is None else run.trajectory[-1], target_np)
            run.extra["plausibility"] = plausibility(run.initial, run.velocity, bounds, spacing, dt, max_speed)
            run.extra["centre_shift"] = (run.initial.mean(0) - target_np.mean(0)).tolist()  # m, initial state - target
            if solver is not None:
                run.solver, info = solver.run(run.initial, run.velocity, K)
                reproduced = None if run.solver is None else run.solver[-1]
                run.extra["solver"] = dict(shape_metrics(reproduced, target_np) or {}, **info)
            log.info("K=%d, %s: model %s, solver %s", K, run.label, run.extra["model"], run.extra.get("solver"))
        title = f"goal {spec.label!r}: {len(target)} particles, K = {K}"
        goal_figure(target_np, runs, bounds, out_dir / f"goal_{name}_K{K}.png", title, up=up)
        goal_animation(target_np, runs, bounds, out_dir / f"goal_{name}_K{K}.gif", fps=fps, up=up)
        files += [f"goal_{name}_K{K}.png", f"goal_{name}_K{K}.gif"]
        per_k[str(K)] = dict(methods={r.label: dict(r.extra, seconds=r.seconds) for r in runs})
    results = dict(goal=vars(spec), particles=len(target), spacing=spacing, steps=horizons, dim=dim,
                   velocity=velocity_si.tolist(),
                   velocity_history=f"every slot {velocity.tolist()} per frame (the velocity x dt {dt:g} s)",
                   physics=dict(solver=None if solver is None else solver.label, note=note,
                                thresholds=dict(overlap=OVERLAP, isolated=ISOLATED), train_max_speed=max_speed),
                   horizons=per_k, files=files + [f"goal_{name}.json"])
    write_whole(out_dir / f"goal_{name}.json", (json.dumps(results, indent=2) + "\n").encode())
    return results


def goal_specs(text=None, **shape) -> list[GoalSpec]:
    """One :class:`GoalSpec` per target: ``text`` a list (``goal.text=[L,N]``) gives one per text,
    each run in turn into its own files; a string (``goal.text=LN``), one. Raises where two
    targets would write the same files."""
    texts = list(text) if isinstance(text, (list, tuple)) else [text]
    if not texts:
        raise ValueError("goal.text=[]: give a text, or a list of texts (goal.text=[L,N]), or null with a mask or points")
    specs = [GoalSpec(text=None if t is None else str(t), **shape) for t in texts]
    names = [file_name(spec) for spec in specs]
    if len(set(names)) < len(names):
        raise ValueError(f"goal.text={texts}: two targets would write the same files (goal_<name>_K<K>.png with "
                         f"names {names}); give texts that differ in their letters or digits")
    return specs


class GoalShaping:
    """:func:`run_goal` as an ``evaluate.py`` task (``task(methods, dataset) -> (results, examples)``),
    e.g. ``task=goal goal.text=LN``; files go to ``<out_dir>/goal_<dataset>/``. The training data's
    largest speed comes from its first ``speed_trajectories`` train trajectories.

    Several texts, ``goal.text=[L,N]``, run one after the other, each into its own files
    (``goal_L_K40.png``, ``goal_N_K40.png``, ...) and its own entry of ``targets`` in the results,
    keyed by the text; the results' other keys are the first target's (what ``report.md`` shows).

    Args: ``out_dir`` (the run folder), ``steps`` (K, one or a list), ``optimisers`` and ``rule``
    (as :func:`run_goal`, ``None``: none), ``physics``, and the :class:`GoalSpec` fields (``text``,
    one or a list, ``mask``, ``points``, ``height``, ``place``, ``lift``, ``velocity``, ...).
    """

    name = "goal"

    def __init__(self, out_dir: str, steps=(20, 40, 100), optimisers: dict | None = None, rule: dict | None = None,
                 physics: bool = True, speed_trajectories: int = 2, **shape):
        self.steps = _horizons(steps)
        self.out_dir, self.optimisers, self.rule, self.physics = out_dir, optimisers, rule, physics
        self.speed_trajectories = speed_trajectories
        self.specs = goal_specs(**shape)
        self.several = isinstance(shape.get("text"), (list, tuple))

    def __call__(self, methods, dataset) -> tuple[dict, dict]:
        from rgns.data.contract import open_split

        models = {m.label: m.model for m in methods if m.model is not None}
        frame = dataset.trajectories[0][0][0].cpu().numpy()
        with open_split(dataset.root, "train") as data:
            train = [data[i] for i in range(min(self.speed_trajectories, len(data)))]
        max_speed = data_max_speed(train, float(dataset.metadata["dt"])) if train else None
        targets = {spec.label: run_goal(models, dataset.metadata, spec, Path(self.out_dir) / f"goal_{dataset.name}",
                                        self.steps, self.optimisers, self.rule, frame, max_speed, self.physics)
                   for spec in self.specs}
        first = next(iter(targets.values()))
        return (dict(first, targets=targets) if self.several else first), {}


def _label(model, extras: dict, path: str) -> str:
    name = getattr(type(model), "display_name", "") or type(model).__name__  # as the models name themselves
    return f"{name} ({Path(path).parent.parent.name})"


def main(argv: list[str] | None = None) -> dict:
    from rgns.data.contract import check_dataset, open_split
    from rgns.evaluation.methods import check_fits, trained_on
    from rgns.training.module import load_simulator

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", action="append", required=True, help="a checkpoint (repeat for several)")
    shape = parser.add_mutually_exclusive_group(required=True)
    shape.add_argument("--text", nargs="+", help="one target per text, each into its own files: --text L N")
    shape.add_argument("--mask", help="an image file (bright shape on dark, or --invert)")
    shape.add_argument("--points", help="a .npy or .txt [M, D] point file, in metres")
    parser.add_argument("--invert", action="store_true")
    parser.add_argument("--height", type=float, default=0.3, help="text/mask height (m)")
    parser.add_argument("--depth", type=float, default=0.1, help="3D extrusion along z (m)")
    parser.add_argument("--place", default="air", choices=["air", "floor", "centre", "none"])
    parser.add_argument("--lift", type=float, default=0.1, help="--place air: the shape's bottom above the floor (m)")
    parser.add_argument("--velocity", type=float, nargs="+", help="the target's velocity at frame K (m/s; default: at rest)")
    parser.add_argument("--steps", type=int, nargs="+", default=[20, 40, 100], help="K, one or several")
    parser.add_argument("--data-root", help="the dataset (default: the first checkpoint's)")
    parser.add_argument("--optimisers", nargs="*", default=["sph"], help="sph, mpm (none: no optimisation baseline)")
    parser.add_argument("--iterations", type=int, default=30, help="the stopping rule's iteration cap")
    parser.add_argument("--no-physics", action="store_true", help="skip the ground-truth solver's check")
    add_out_arguments(parser)
    args = parser.parse_args(argv)
    refuse_earlier_out(parser, args)
    if min(args.steps) < 1 or args.iterations < 1:
        parser.error(f"--steps {' '.join(map(str, args.steps))} and --iterations {args.iterations}: each must be at least 1")
    if not set(args.optimisers) <= {"sph", "mpm"}:
        parser.error(f"--optimisers {' '.join(args.optimisers)}: the kinds are sph and mpm")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(1)

    models, root = {}, args.data_root
    for path in args.ckpt:
        model, extras = load_simulator(path)
        label = _label(model, extras, path)
        models[label if label not in models else f"{label} {Path(path).name}"] = model  # two of one run stay apart
        root = root or trained_on(path, extras["data_root"], extras["data_root_relative"])
    if root is None:
        raise SystemExit("the checkpoint does not name its dataset: pass --data-root")
    contents = check_dataset(root, splits=("train",))
    for path, model in zip(args.ckpt, models.values()):
        check_fits(model, path, contents.metadata, contents.particle_types["train"], str(Path(root) / "train.h5"))
    metadata = contents.metadata
    with open_split(root, "train") as data:
        frame = data[0][0][0]
        max_speed = data_max_speed([data[i] for i in range(min(2, len(data)))], float(metadata["dt"]))
    try:
        specs = goal_specs(text=args.text, mask=args.mask, points=args.points, height=args.height, depth=args.depth,
                           place=args.place, lift=args.lift, velocity=args.velocity, invert=args.invert)
    except ValueError as error:
        parser.error(str(error))
    targets = {}
    for spec in specs:
        results = targets[spec.label] = run_goal(
            models, metadata, spec, args.out, args.steps, {kind: {} for kind in args.optimisers},
            dict(max_iterations=args.iterations), frame, max_speed, not args.no_physics)
        for K, at in results["horizons"].items():
            for label, row in at["methods"].items():
                model, solver = row["model"] or {}, row.get("solver") or {}
                print(f"{spec.label!r} K={K:>4} {label:32s} chamfer model={model.get('chamfer')} "
                      f"solver={solver.get('chamfer')} seconds={row['seconds']:.3f} status={row.get('status')} "
                      f"flags={row['plausibility']['flags']}")
        print(f"wrote {', '.join(str(Path(args.out) / f) for f in results['files'])}")
    return targets[specs[0].label] if len(specs) == 1 else targets


if __name__ == "__main__":
    main()
