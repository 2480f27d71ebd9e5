"""Where methods fail: rollouts on conditions no model was trained on (``evaluate.py task=generalise``).

For a generated dataset (its ``metadata["generator"]`` records the scene), each condition changes
the scene, generates a few test trajectories of it with the dataset's own solver, and rolls every
method out on them from the same frame as the ordinary test (no retraining; a trained model is
told the condition's box, as its walls are an input):

- ``longer``: the training scene itself, rolled out for ``steps`` steps (1,000 by default: more
  than three times the ordinary test's horizon): the control, and the long-horizon stability;
- ``wide_box``: the box twice as wide (its first axis), the bodies drawn as before;
- ``more_bodies``: twice the bodies and twice the particles (within the solver's capacity);
- ``full``: the scene's ``<name>_full`` preset (``conf/scene``): the original dataset's scale,
  more particles and longer trajectories, in its own box;
- ``ramps_outside``: scenes with ramps only: ramps steeper than any in training (5 to 25 degrees
  past the steepest).

Per condition and method: rollout MSE, error against step, stable steps and where each rollout
broke and why (:func:`classify_break`: non-finite, left the box, exploded, compressed, stalled),
beside the dataset's solver at a coarser grid and the training-free baselines, and the state at
the break of the first trajectory (``generalise_<dataset>_<condition>.png``). Every condition's
trajectories are ``start + steps + 1`` frames long, generated under ``<out_dir>/conditions/``
(deterministic: ``seed``).

Both directions of time (``directions``): on the conditions listed in ``inverse_conditions``
(``longer`` by default) every method that can run backwards (its model is ``bidirectional``:
R-GNS, Sep-GNS's backward network, the training-free baselines' mirrored rules; see
:func:`no_inverse`) is also rolled back ``steps`` steps from each trajectory's last frame
(:func:`inverse_rollout`), the truth run backwards as the reference, and its breaks are named by
the same :func:`classify_break`: a speed is the distance between consecutive frames whichever way
time runs, so "exploded" is a kinetic energy far above the true past's greatest and "stalled" an
inferred past at rest while the true past moves. The methods without an inverse (forward-only
networks, the solver) are listed with the reason (``without_inverse``).

Per condition and direction, each method that broke is drawn at its first break over the
trajectories beside the truth at that frame (:func:`break_picture`,
``generalise_<dataset>_<condition>_<direction>_breaks.png``; a 3D scene in two views).
"""
from __future__ import annotations

import contextlib
import copy
import logging
import math
import textwrap
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch
from torch import Tensor

from rgns.data.contract import KINEMATIC
from rgns.data.generate import generate_dataset, scene_config
from rgns.evaluation.metrics import density_ratio, mse_per_step
from rgns.evaluation.plots import PANELS_PER_ROW, save_figure, up_axis, view_name, views
from rgns.evaluation.tasks import Dataset, finite, mean_or_none, stride_of
from rgns.models import State
from rgns.training.rollouts import fill_frames

log = logging.getLogger(__name__)

CAUSES = ("non-finite", "left the box", "exploded", "compressed", "stalled")
CONDITIONS = ("longer", "wide_box", "more_bodies", "full", "ramps_outside")
HALF_GRID = {"resolutions": [0.5], "floor_perturbation": None}  # the default solver reference: half its grid
DIRECTIONS = ("forward", "inverse")


@dataclass
class BreakRule:
    """When a rollout counts as broken, and why.

    Args:
        margin_radii: left the box: a moving particle this many connectivity radii outside it.
        energy_factor: exploded: the mean kinetic energy (per-frame speed squared) this many times
            the true trajectory's greatest.
        compression: compressed: the densest cell of side R holds this many times the most the
            true trajectory ever holds in one.
        stall_fraction: stalled: over ``window`` steps the mean speed stays under this fraction
            of the truth's, while the truth moves at least ``moving`` of its fastest (windowed).
    """

    margin_radii: float = 2.0
    energy_factor: float = 100.0
    compression: float = 3.0
    stall_fraction: float = 0.1
    window: int = 20
    moving: float = 0.1


def densest_cells(positions: Tensor, lower: Tensor, radius: float) -> Tensor:
    """Per frame of ``[T, N, D]``, the most particles in one cell of a grid of side ``radius``
    anchored at ``lower [D]``.  ``[T]`` (non-finite frames count 0)."""
    counts = []
    for frame in positions:
        finite = torch.isfinite(frame).all(-1)
        if not bool(finite.any()):
            counts.append(0)
            continue
        cell = torch.floor((frame[finite] - lower) / radius).clamp(-1e6, 1e6).long()
        counts.append(int(torch.unique(cell, dim=0, return_counts=True)[1].max()))
    return torch.tensor(counts)


def _windowed(values: Tensor, window: int) -> Tensor:
    """Means over each run of ``window`` consecutive values (``len - window + 1`` of them)."""
    if len(values) < window:
        return values.new_zeros(0)
    return values.unfold(0, window, 1).mean(-1)


def classify_break(predicted: Tensor, truth: Tensor, particle_type: Tensor, bounds: Tensor, radius: float,
                   rule: BreakRule = BreakRule(), before: Tensor | None = None) -> tuple[int | None, str | None]:
    """The first step (0-based frame of ``predicted [T, N, D]``) at which a rollout is broken, and
    the cause (one of :data:`CAUSES`; the first in that order where several begin at that step),
    or ``(None, None)``. ``truth [T, N, D]``: the true frames of the same steps; ``before [N, D]``:
    the frame the rollout started from (speeds of the first step), else the first frame's speed is 0."""
    moving = particle_type != KINEMATIC
    x, y = predicted[:, moving].float(), truth[:, moving].float()
    start = (x[:1] if before is None else before[moving].float().unsqueeze(0))
    first = {}
    bad = ~torch.isfinite(x).flatten(1).all(1)
    first["non-finite"] = bad
    margin = rule.margin_radii * radius
    first["left the box"] = ((x < bounds[:, 0] - margin) | (x > bounds[:, 1] + margin)).flatten(1).any(1)
    speed_x = torch.diff(torch.cat([start, x]), dim=0).pow(2).sum(-1)  # [T, M] squared per-frame speed
    speed_y = torch.diff(torch.cat([start if before is not None else y[:1], y]), dim=0).pow(2).sum(-1)
    energy_x, energy_y = speed_x.mean(-1), speed_y.mean(-1)
    first["exploded"] = energy_x > rule.energy_factor * float(energy_y.max().clamp(min=1e-30))
    dense_truth = int(densest_cells(y, bounds[:, 0], radius).max())
    first["compressed"] = densest_cells(x, bounds[:, 0], radius).to(x.device) > rule.compression * max(dense_truth, 1)
    mean_x, mean_y = speed_x.sqrt().mean(-1), speed_y.sqrt().mean(-1)
    wx, wy = _windowed(mean_x, rule.window), _windowed(mean_y, rule.window)
    stalled = torch.zeros(len(x), dtype=torch.bool, device=x.device)
    if len(wy):
        stall = (wx < rule.stall_fraction * wy) & (wy >= rule.moving * float(wy.max()))
        stalled[: len(stall)] = stall & torch.isfinite(wx)
    first["stalled"] = stalled
    found = [(int(hits[0]), CAUSES.index(cause), cause) for cause, mask in first.items()
             if len(hits := mask.nonzero().flatten())]
    if not found:
        return None, None
    step, _, cause = min(found)
    return step, cause


def no_inverse(method) -> str | None:
    """Why ``method`` cannot run backwards in time, or ``None`` where it can: a model that is
    ``bidirectional`` (R-GNS, Sep-GNS with its backward network, the baselines' mirrored rules)."""
    if method.model is None:
        return "the dataset's solver runs forward in time only"
    if not method.bidirectional:
        return f"{type(method.model).__name__} simulates forward in time only"
    return None


@torch.no_grad()
def inverse_rollout(method, position: Tensor, particle_type: Tensor, end: int, steps: int) -> Tensor:
    """Frames ``end - 1, end - 2, .., end - steps`` of a trajectory, inferred back from its true
    state at frame ``end`` by ``method``'s inverse steps, kinematic particles at their true
    positions. A model trained on every s-th frame (its ``stride``) steps back s frames at a time
    from the state built of frames ``end, end - s, ..``; the frames between its steps are filled in
    along straight lines (:func:`~rgns.training.rollouts.fill_frames`).

    :meth:`~rgns.models.Simulator.inverse_rollout` stops as the forward rollout does: one that
    collapses (its densest cell of side R past ``model.collapse_factor`` times the first state's)
    repeats its last frame from there, one that turns non-finite is NaN from there.

    Shapes:
        position: ``[T, N, D]`` ground truth  ->  ``[steps, N, D]`` inferred frames end-1, end-2, ..
    """
    model, stride = method.model, stride_of(method)
    if not 1 <= steps <= end:
        raise ValueError(f"{steps} inverse steps back from frame {end}: between 1 and {end} "
                         "(the truth stops at frame 0)")
    phase = position[end % stride :: stride]  # frame end - s j is entry last - j
    last, n, k = end // stride, math.ceil(steps / stride), model.history
    if last < k:
        raise ValueError(f"{method.label}: an inverse rollout from frame {end} needs {k} velocities of history "
                         f"{stride} frame(s) apart before it (frame >= {stride * k})")
    state = State.from_positions(phase[last - k : last + 1], particle_type)
    # row i: the phase's frame last - 1 - i, where kinematic particles stand (Simulator.inverse_rollout)
    inferred = model.inverse_rollout(state, n, phase[:last].flip(0))
    predicted = fill_frames(position[end], inferred, stride)[:steps]
    kinematic = particle_type == KINEMATIC
    predicted[:, kinematic] = position[end - steps : end].flip(0)[:, kinematic]
    return predicted


def _panel(ax, points: np.ndarray, kinematic: np.ndarray, low: np.ndarray, high: np.ndarray, colour: str,
           title: str) -> None:
    """Particles ``[N, 2]`` in the box ``low..high`` with a margin of a tenth of it; those beyond
    the margin (or not finite) in red on its edge, counted in the title."""
    margin = 0.1 * (high - low)
    shown_low, shown_high = low - margin, high + margin
    outside = ~np.isfinite(points).all(1) | ((points < shown_low) | (points > shown_high)).any(1)
    points = np.clip(np.nan_to_num(points, nan=shown_low[0]), shown_low, shown_high)
    colours = np.where(outside, "tab:red", np.where(kinematic, "0.75", colour))
    ax.scatter(points[:, 0], points[:, 1], s=np.where(outside, 8.0, 1.5), c=colours, clip_on=False)
    ax.add_patch(plt.Rectangle(low, *(high - low), fill=False, lw=0.6, ec="0.3"))
    ax.set_xlim(shown_low[0], shown_high[0])
    ax.set_ylim(shown_low[1], shown_high[1])
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.set_title(title + (f"\n{int(outside.sum())} off the chart" if outside.any() else ""), fontsize=7)


def break_picture(breaks: dict, bounds: Tensor, up: int, title: str, path: Path) -> bool:
    """Each broken method's state at its first break beside the truth at that frame, written to
    ``path`` (PNG); ``False``, and no file, where no method broke.

    ``breaks``: ``{label: {"step", "cause", "trajectory", "frame", "predicted" [N, D], "truth"
    [N, D], "particle_type" [N]}}``, the step 0-based as in the tables. A 2D scene: a pair of panels (method, truth) per method, three
    methods a row; a 3D scene: a row per method, the pair seen from the front (the first horizontal
    axis against the ``up`` axis) and from above. Moving particles blue (the method's) or dark
    grey (the truth's), kinematic ones light grey."""
    if not breaks:
        return False
    bounds = np.asarray(bounds, dtype=float)
    projections = views(len(bounds), up)
    per_method = 2 * len(projections)
    methods_a_row = max(1, PANELS_PER_ROW // per_method)
    columns = per_method * min(len(breaks), methods_a_row)
    rows = math.ceil(len(breaks) / methods_a_row)
    sizes = [(bounds[v, 1] - bounds[v, 0]) / (bounds[h, 1] - bounds[h, 0]) for h, v, _ in projections]
    width = 2.3 * columns
    title = textwrap.fill(title, max(30, int(12 * width)))  # about 12 characters an inch at 9 points
    lines = title.count("\n") + 1
    fig, axes = plt.subplots(rows, columns, figsize=(width, rows * (2.3 * max(sizes) + 0.8) + 0.25 + 0.15 * lines),
                             squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    for m, (label, broke) in enumerate(breaks.items()):
        kinematic = np.asarray(broke["particle_type"]) == KINEMATIC
        row, first = divmod(m, methods_a_row)
        for v, view in enumerate(projections):
            h, u, name = view
            seen = f"\n{view_name(view)}" if name else ""
            low, high = bounds[[h, u], 0], bounds[[h, u], 1]
            for p, (who, points, colour) in enumerate((
                    (f"{label}\n{broke['cause']} at step {broke['step']}\n(trajectory {broke['trajectory']}, "
                     f"frame {broke['frame']}){seen}", broke["predicted"], "tab:blue"),
                    (f"truth, frame {broke['frame']}{seen}", broke["truth"], "0.3"))):
                ax = axes[row, first * per_method + 2 * v + p]
                _panel(ax, np.asarray(points, dtype=float)[:, [h, u]], kinematic, low, high, colour, who)
    fig.suptitle(title, fontsize=9)
    save_figure(fig, path)
    return True


@contextlib.contextmanager
def in_box(model, bounds: Tensor):
    """A model's walls moved to ``bounds [D, 2]`` for the block (its ``bounds`` buffer), then back."""
    if model is None or not hasattr(model, "bounds"):
        yield
        return
    kept = model.bounds.clone()
    model.bounds.copy_(bounds.to(kept))
    try:
        yield
    finally:
        model.bounds.copy_(kept)


def condition_scene(name: str, params: dict, steps: int, start: int) -> tuple[dict | None, str]:
    """The scene config of condition ``name`` made from the dataset's generator ``params``, and a
    sentence saying what it changes; ``(None, why)`` where the condition does not apply."""
    cfg = copy.deepcopy(params)
    if name == "longer":
        return cfg, f"the training scene, {steps} steps from frame {start}"
    if name == "wide_box":
        (low, high), *rest = cfg["bounds"]
        cfg["bounds"] = [[low, low + 2 * (high - low)], *rest]
        return cfg, f"the box twice as wide: {cfg['bounds']} (training: {params['bounds']})"
    if name == "more_bodies":
        if "num_bodies" not in cfg:
            return None, f"scene {params.get('name')} draws no bodies"
        low, high = cfg["num_bodies"]
        cfg["num_bodies"] = [2 * low, 2 * high]
        capacity = int(cfg.get("capacity", 10**9))
        cfg["particles"] = [min(2 * p, capacity) for p in cfg.get("particles", [0, capacity])]
        return cfg, f"{cfg['num_bodies']} bodies of {cfg['particles']} particles (training: {low}-{high} bodies)"
    if name == "full":
        preset = f"{params.get('name')}_full"
        try:
            full = scene_config(preset)
        except Exception as error:  # noqa: BLE001 - a scene without a full preset skips the condition
            return None, f"no preset {preset} ({type(error).__name__})"
        return full, f"the {preset} preset: {full.get('particles')} particles in {full.get('bounds')}"
    if name == "ramps_outside":
        if max(cfg.get("num_ramps", [0])) < 1:
            return None, f"scene {params.get('name')} has no ramps"
        steepest = float(cfg.get("ramp_angle", [10.0, 40.0])[1])
        cfg["ramp_angle"] = [steepest + 5.0, min(steepest + 25.0, 75.0)]
        return cfg, f"ramps at {cfg['ramp_angle']} degrees (training: {params.get('ramp_angle')})"
    raise ValueError(f"task.generalise.conditions: unknown condition {name!r}; known: {', '.join(CONDITIONS)}")


class Generalisation:
    """The ``generalise`` task (see the module's docs).

    Args:
        out_dir: where the conditions' datasets are generated (``conditions/<dataset>_<name>``)
            and the break pictures written.
        conditions: names among :data:`CONDITIONS`.
        trajectories: test trajectories per condition.
        steps: rollout steps from the dataset's start frame (capped by each trajectory's length),
            and back from each trajectory's last frame.
        seed: of the conditions' generation.
        references: the conditions' solver references (``SolverReferences`` arguments; by default
            the solver at half its grid); ``None`` or empty: none (``rgns.failures`` measures them
            once per benchmark, not in every run's evaluation).
        rule: :class:`BreakRule` fields.
        directions: among :data:`DIRECTIONS`: ``forward`` on every condition, ``inverse`` on those
            in ``inverse_conditions`` that run.
        inverse_conditions: the conditions also rolled backwards.
        conditions_dir: where the conditions' datasets are generated (``None``: ``<out_dir>/conditions``);
            one folder shared by several evaluations generates each condition once (a complete dataset
            of the same settings is reused, :func:`~rgns.data.generate.generate_dataset`).
    """

    name = "generalise"
    compares_references = False  # each condition gets references of its own
    strided = True  # rollouts through Method.forward_rollout, which steps a strided model at its stride

    def __init__(self, out_dir: str, conditions=("longer", "wide_box", "more_bodies", "full"), trajectories: int = 2,
                 steps: int = 1000, seed: int = 7, references: dict | None = HALF_GRID, rule: dict | None = None,
                 directions=("forward", "inverse"), inverse_conditions=("longer",), conditions_dir: str | None = None):
        unknown = [c for c in [*conditions, *inverse_conditions] if c not in CONDITIONS]
        if unknown:
            raise ValueError(f"task.generalise.conditions / inverse_conditions: unknown {unknown}; known: "
                             f"{', '.join(CONDITIONS)}")
        if not directions or any(d not in DIRECTIONS for d in directions):
            raise ValueError(f"task.generalise.directions={list(directions)}: one or both of {', '.join(DIRECTIONS)}")
        self.out_dir, self.conditions, self.trajectories = Path(out_dir), list(conditions), int(trajectories)
        self.steps, self.seed = int(steps), int(seed)
        self.references = references if references else None
        self.rule = BreakRule(**(rule or {}))
        self.directions, self.inverse_conditions = [d for d in DIRECTIONS if d in directions], list(inverse_conditions)
        self.conditions_dir = self.out_dir / "conditions" if conditions_dir is None else Path(conditions_dir)

    def __call__(self, methods, dataset) -> tuple[dict, dict]:
        from rgns.evaluation.references import SolverReferences

        generator = dataset.metadata.get("generator")
        settings = dict(conditions=self.conditions, trajectories=self.trajectories, steps=self.steps, seed=self.seed,
                        start=dataset.start, rule=vars(self.rule), references=self.references,
                        directions=self.directions, inverse_conditions=self.inverse_conditions)
        if not isinstance(generator, dict) or not isinstance(generator.get("params"), dict):
            return dict(settings=settings, note="no generator in the metadata: no scene to change", conditions={}), {}
        results, examples = {}, {}
        for name in self.conditions:
            cfg, what = condition_scene(name, generator["params"], self.steps, dataset.start)
            if cfg is None:
                results[name] = dict(skipped=what)
                continue
            root = self.conditions_dir / f"{dataset.name}_{name}"
            frames = dataset.start + self.steps + 1  # every condition as long as the rollouts
            log.info("generalise: %s: %s (generating %s)", name, what, root)
            generate_dataset(cfg, root, num_frames=frames, seed=self.seed, workers=1, progress=False,
                             splits={"train": 1, "valid": 1, "test": self.trajectories})
            condition = Dataset.load(str(root), "test", self.trajectories, dataset.start, dataset.start,
                                     dataset.trajectories[0][0].device)
            references = (SolverReferences(**self.references)(condition)[0] if self.references else [])
            results[name] = {}
            for direction in self.directions:
                if direction == "inverse" and name not in self.inverse_conditions:
                    continue
                section, example, breaks = self.run(methods + references, condition, direction)
                picture = f"generalise_{dataset.name}_{name}_{direction}_breaks.png"
                title = (f"{dataset.name}, {name}, {direction}: each method that broke, at its first break over the "
                         "trajectories, beside the truth at that frame")
                up = up_axis(condition.metadata)
                drawn = break_picture(breaks, condition.bounds, up, title, self.out_dir / picture)
                section["break_picture"] = picture if drawn else None
                if direction == "forward":
                    results[name].update(section)
                    examples[name] = example
                else:
                    results[name]["inverse"] = section
            results[name]["description"] = what
            results[name]["particles"] = [int(p.shape[1]) for p, _ in condition.trajectories]
        return dict(settings=settings, conditions=results), examples

    def rollout(self, method, condition, index: int, direction: str) -> tuple[Tensor, Tensor, Tensor, int, int]:
        """One rollout of test trajectory ``index``: ``(predicted, truth, before, first, sign)``,
        the predicted and true frames ``[L, N, D]`` of its steps, the true frame it started from
        ``[N, D]``, and the frame of step ``s`` being ``first + sign * s``. Forward: from frame
        ``start``; inverse: back from the trajectory's last frame, the truth run backwards."""
        position, particle_type = condition.trajectories[index]
        if direction == "forward":
            length = min(self.steps, len(position) - 1 - condition.start)
            truth = position[condition.start + 1 : condition.start + 1 + length]
            return (method.forward_rollout(condition, index, length), truth, position[condition.start],
                    condition.start + 1, 1)
        end = len(position) - 1
        length = min(self.steps, end)
        truth = position[end - length : end].flip(0)  # frames end-1, end-2, .., end-length
        return inverse_rollout(method, position, particle_type, end, length), truth, position[end], end - 1, -1

    def run(self, methods, condition, direction: str = "forward") -> tuple[dict, dict, dict]:
        """Every method on every trajectory of one condition in one direction: its metrics (and, in
        the inverse, the methods without an inverse and why), the first trajectory's frame at
        each method's break (or its last) for the forward picture, and each broken method's state
        at its first break over the trajectories (:func:`break_picture`'s ``breaks``)."""
        radius = float(condition.metadata["default_connectivity_radius"])
        bounds = condition.bounds
        rows, without, breaks = {}, {}, {}
        example = dict(truth={}, predicted={}, particle_type=condition.trajectories[0][1].cpu(), bounds=bounds.cpu())
        for method in methods:
            if direction == "inverse" and (why := no_inverse(method)):
                without[method.label] = why
                continue
            per, broken = [], []
            for i, (position, particle_type) in enumerate(condition.trajectories):
                with in_box(method.model, bounds), torch.no_grad():
                    predicted, truth, before, first, sign = self.rollout(method, condition, i, direction)
                length = len(truth)
                step, cause = classify_break(predicted, truth, particle_type, bounds, radius, self.rule, before=before)
                per_step = mse_per_step(predicted, truth)
                moving = particle_type != KINEMATIC
                density_end = density_ratio(predicted[-1, moving], truth[-1, moving], radius)
                per.append(dict(rollout_mse=finite(per_step.mean()), mse_per_step=[finite(v) for v in per_step],
                                stable_steps=length if step is None else step, steps=length, break_step=step,
                                cause=cause, density_end=density_end))
                if step is not None:
                    broken.append(dict(step=step, cause=cause, trajectory=i, frame=first + sign * step,
                                       predicted=predicted[step].cpu().numpy(), truth=truth[step].cpu().numpy(),
                                       particle_type=particle_type.cpu().numpy()))
                if i == 0:
                    at = length - 1 if step is None else step
                    example["predicted"][method.label] = (at, predicted[at].cpu().numpy())
                    example["truth"][method.label] = truth[at].cpu().numpy()
            rows[method.label] = _aggregate(per)
            if broken:  # the one _aggregate names first_break
                breaks[method.label] = min(broken, key=lambda b: (b["step"], b["cause"], b["trajectory"]))
        section = dict(methods=rows)
        if direction == "inverse":
            section.update(from_frames=[len(p) - 1 for p, _ in condition.trajectories], without_inverse=without)
        return section, example, breaks


def _aggregate(per: list[dict]) -> dict:
    longest = max(r["steps"] for r in per)
    curve = []
    for s in range(longest):
        values = [r["mse_per_step"][s] for r in per if s < r["steps"] and r["mse_per_step"][s] is not None]
        curve.append(float(np.mean(values)) if values else None)
    mses = [r["rollout_mse"] for r in per]
    broken = [(r["break_step"], r["cause"]) for r in per if r["break_step"] is not None]
    return dict(rollout_mse=mean_or_none(mses),
                rollout_mse_per_trajectory=mses, mse_per_step=curve,
                stable_steps=min(r["stable_steps"] for r in per),
                breaks=[dict(step=r["break_step"], cause=r["cause"]) for r in per],
                first_break=None if not broken else dict(zip(("step", "cause"), min(broken))),
                density_end=[r["density_end"] for r in per], steps=longest)
