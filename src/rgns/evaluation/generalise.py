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
"""
from __future__ import annotations

import contextlib
import copy
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rgns.data.contract import KINEMATIC
from rgns.data.generate import generate_dataset, scene_config
from rgns.evaluation.metrics import density_ratio, mse_per_step
from rgns.evaluation.tasks import Dataset, finite, mean_or_none

log = logging.getLogger(__name__)

CAUSES = ("non-finite", "left the box", "exploded", "compressed", "stalled")
CONDITIONS = ("longer", "wide_box", "more_bodies", "full", "ramps_outside")


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
        out_dir: where the conditions' datasets are generated (``conditions/<dataset>_<name>``).
        conditions: names among :data:`CONDITIONS`.
        trajectories: test trajectories per condition.
        steps: rollout steps from the dataset's start frame (capped by each trajectory's length).
        seed: of the conditions' generation.
        references: the conditions' solver references (``SolverReferences`` arguments); ``None``: none.
        rule: :class:`BreakRule` fields.
    """

    name = "generalise"
    compares_references = False  # each condition gets references of its own
    strided = True  # rollouts through Method.forward_rollout, which steps a strided model at its stride

    def __init__(self, out_dir: str, conditions=("longer", "wide_box", "more_bodies", "full"), trajectories: int = 2,
                 steps: int = 1000, seed: int = 7, references: dict | None = None, rule: dict | None = None):
        unknown = [c for c in conditions if c not in CONDITIONS]
        if unknown:
            raise ValueError(f"task.generalise.conditions: unknown {unknown}; known: {', '.join(CONDITIONS)}")
        self.out_dir, self.conditions, self.trajectories = Path(out_dir), list(conditions), int(trajectories)
        self.steps, self.seed = int(steps), int(seed)
        self.references = {"resolutions": [0.5], "floor_perturbation": None} if references is None else references
        self.rule = BreakRule(**(rule or {}))

    def __call__(self, methods, dataset) -> tuple[dict, dict]:
        from rgns.evaluation.references import SolverReferences

        generator = dataset.metadata.get("generator")
        settings = dict(conditions=self.conditions, trajectories=self.trajectories, steps=self.steps, seed=self.seed,
                        start=dataset.start, rule=vars(self.rule), references=self.references)
        if not isinstance(generator, dict) or not isinstance(generator.get("params"), dict):
            return dict(settings=settings, note="no generator in the metadata: no scene to change", conditions={}), {}
        results, examples = {}, {}
        for name in self.conditions:
            cfg, what = condition_scene(name, generator["params"], self.steps, dataset.start)
            if cfg is None:
                results[name] = dict(skipped=what)
                continue
            root = self.out_dir / "conditions" / f"{dataset.name}_{name}"
            frames = dataset.start + self.steps + 1  # every condition as long as the rollouts
            log.info("generalise: %s: %s (generating %s)", name, what, root)
            generate_dataset(cfg, root, num_frames=frames, seed=self.seed, workers=1, progress=False,
                             splits={"train": 1, "valid": 1, "test": self.trajectories})
            condition = Dataset.load(str(root), "test", self.trajectories, dataset.start, dataset.start,
                                     dataset.trajectories[0][0].device)
            references = (SolverReferences(**self.references)(condition)[0] if self.references else [])
            results[name], examples[name] = self.run(methods + references, condition)
            results[name]["description"] = what
            results[name]["particles"] = [int(p.shape[1]) for p, _ in condition.trajectories]
        return dict(settings=settings, conditions=results), examples

    def run(self, methods, condition) -> tuple[dict, dict]:
        """Every method on every trajectory of one condition: its metrics, and the first
        trajectory's frame at each method's break (or its last) for the picture."""
        radius = float(condition.metadata["default_connectivity_radius"])
        bounds = condition.bounds
        rows, example = {}, dict(truth={}, predicted={}, particle_type=condition.trajectories[0][1].cpu(),
                                 bounds=bounds.cpu())
        for method in methods:
            per = []
            for i, (position, particle_type) in enumerate(condition.trajectories):
                length = min(self.steps, len(position) - 1 - condition.start)
                truth = position[condition.start + 1 : condition.start + 1 + length]
                with in_box(method.model, bounds), torch.no_grad():
                    predicted = method.forward_rollout(condition, i, length)
                step, cause = classify_break(predicted, truth, particle_type, bounds, radius, self.rule,
                                             before=position[condition.start])
                per_step = mse_per_step(predicted, truth)
                moving = particle_type != KINEMATIC
                per.append(dict(rollout_mse=finite(per_step.mean()), mse_per_step=[finite(v) for v in per_step],
                                stable_steps=length if step is None else step, steps=length, break_step=step,
                                cause=cause, density_end=density_ratio(predicted[-1, moving], truth[-1, moving], radius)))
                if i == 0:
                    at = length - 1 if step is None else step
                    example["predicted"][method.label] = (at, predicted[at].cpu().numpy())
                    example["truth"][method.label] = truth[at].cpu().numpy()
            rows[method.label] = _aggregate(per)
        return dict(methods=rows), example


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
