"""The inverse comparison: feed-forward inverse inference against the optimisation baselines,
for the same targets and horizons K, and where each method stops working.

For each test trajectory and each K, the target is the true state at frame ``t0 + K``:

- feed-forward (every bidirectional model: R-GNS, Sep-GNS): K inverse steps from the true state
  (positions and velocity history), timed;
- optimisation (``optimisers``): Adam on the initial state (position and velocity; velocity
  history for a learned simulator) through a differentiable simulator, from the target state
  itself as the first guess, asked to reach the target positions and newest velocity at frame K,
  run to the one stopping rule (:class:`~rgns.inverse.optimise.StoppingRule`); variants
  ``sph`` (differentiable WCSPH, the paper's baseline), ``mpm`` (MLS-MPM water in torch autograd,
  :mod:`rgns.inverse.mpm`) and ``learned`` (gradient descent through a trained forward
  simulator, Allen et al. 2022).

Every method is then judged the same way: K forward frames of its own forward simulator from the
initial state it found, against the true target (**consistency MSE**), and that initial state
against the true frame ``t0`` (**inverse MSE**). A horizon is *stable* for a method while its
consistency MSE stays under ``threshold`` (and, for an optimiser, the solve did not fail);
**max stable steps** is the largest K such that every K' <= K tried is stable. The time ratio at
``table_horizon`` (the paper: K = 40) is each optimiser's time over each feed-forward model's.
Optionally, long forward and inverse rollouts (``stability_steps``, 1,000 and more) report how
many steps each model stays stable.

Entry points: :func:`compare_inverse` (in-memory trajectories), :func:`run_inverse_comparison`
(a dataset folder), and :class:`InverseComparison` (an ``evaluate.py`` task:
``task(methods, dataset) -> (results, examples)``).
"""
from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from rgns.data.contract import KINEMATIC, SPLITS, DatasetError, check_dataset, open_split, read_metadata
from rgns.inverse.feedforward import feed_forward_inverse, forward_stability, inverse_stability
from rgns.inverse.optimise import StoppingRule, optimise_initial_state
from rgns.inverse.simulators import LearnedSimulator, SPHSimulator, sph_for_dataset
from rgns.evaluation.plots import save_figure, write_whole
from rgns.models import State, count_parameters

log = logging.getLogger(__name__)

DEFAULT_OPTIMISERS = {"sph": {}}


def chosen_optimisers(optimisers) -> dict:
    """The optimisers a task's configuration asks for, ``{kind: options}``: ``None`` (or an empty
    mapping) is none, and a kind set to ``None`` is left out, so that ``task.<task>.optimisers=null``
    and ``task.<task>.optimisers.mpm=null`` mean what they say on the command line (a Hydra override
    ``optimisers={}`` merges into the preset's mapping instead of replacing it)."""
    if optimisers is None:
        return {}
    if not hasattr(optimisers, "items"):
        raise ValueError(f"optimisers={optimisers!r}: give a mapping {{kind: options}} (kinds sph, mpm, learned) or null")
    return {str(kind): dict(options or {}) for kind, options in optimisers.items() if options is not None}


def _mse(x: Tensor, y: Tensor) -> float | None:
    value = float((x.double() - y.double()).pow(2).mean())
    return value if math.isfinite(value) else None


def _optimiser_simulator(kind: str, options: dict, metadata: dict, models: dict, num_particles: int,
                         particle_type: Tensor):
    """The differentiable simulator of an optimisation variant, and its label."""
    if kind == "sph":
        solver = sph_for_dataset(metadata, capacity=num_particles, substeps=options.get("substeps", 25))
        return SPHSimulator(solver), "SPH + Adam"
    if kind == "mpm":
        from rgns.inverse.mpm import TorchMPM

        return TorchMPM.for_dataset(metadata, **options.get("solver", {})), "MPM + Adam"
    if kind == "learned":
        label = options.get("model") or next(iter(models))
        return LearnedSimulator(models[label], particle_type), f"{label} + Adam"
    raise ValueError(f"optimiser kind must be 'sph', 'mpm' or 'learned', got {kind!r}")


def _warm_up(simulator, position: Tensor, velocity: Tensor) -> None:
    """One frame forward and backward, so that compilation (Taichi) is not timed."""
    x, v = position.clone().requires_grad_(True), velocity.clone().requires_grad_(True)
    final_x, final_v = simulator.simulate(x, v, 1)
    (final_x.sum() + final_v.sum()).backward()


def compare_inverse(models: dict, metadata: dict, trajectories: list[tuple[Tensor, Tensor]], horizons,
                    start: int | None = None, optimisers: dict | None = None, rule: dict | None = None,
                    threshold: float = 1e-3, table_horizon: int = 40, stability_steps: int = 0,
                    divergence: dict | None = None, budget_iterations: int = 0,
                    out_dir: str | Path | None = None) -> dict:
    """The inverse comparison on in-memory trajectories (see the module docstring).

    Args:
        models: ``{label: Simulator}``; bidirectional ones run feed-forward inverse inference.
        metadata: the dataset's metadata. trajectories: ``[(position [T, N, D], particle_type [N])]``.
        horizons: the K tried. start: t0 (default: k, the first frame with a full history).
        optimisers: ``{kind: options}`` with kind ``sph``, ``mpm`` or ``learned`` (options:
            ``lr``, ``velocity_lr``, ``clip``, ``schedule``, ``substeps`` (sph), ``model`` (learned),
            ``horizons`` (a subset of K for this optimiser)); a kind set to ``None`` is left out.
            Default: ``{"sph": {}}``.
        rule: :class:`StoppingRule` fields, shared by every optimiser and target.
        threshold: consistency MSE under which a horizon is stable.
        table_horizon: the K of the table and the time ratio (capped by the horizons run).
        stability_steps: long forward/inverse rollouts of this length per model (0: skip).
        divergence: ``margin_radii``, ``energy_factor`` for the long rollouts.
        budget_iterations: also time each optimiser at the table horizon for exactly this many
            iterations with the failure checks off (the cost of trying, whatever the verdict), and
            its ratio to each feed-forward model (0: skip).
        out_dir: where ``inverse_comparison.{json,md}`` and ``inverse_k_sweep.png`` go (None: nowhere).
    """
    optimisers = chosen_optimisers(DEFAULT_OPTIMISERS if optimisers is None else optimisers)
    stopping = StoppingRule(**(rule or {}))
    feed_forward = {label: m for label, m in models.items() if m.bidirectional}
    history = next(iter(models.values())).history if models else 5
    start = history if start is None else start
    if not trajectories:
        raise ValueError("compare_inverse: no trajectories to compare on")
    if not horizons or min(horizons) < 1:
        raise ValueError(f"horizons={list(horizons)}: each K must be at least 1")
    longest = min(len(p) for p, _ in trajectories) - 1 - start
    dropped = {K: f"longer than the {longest} frames after t0 = {start} of the shortest trajectory "
                  f"({longest + 1 + start} frames)" for K in sorted(set(horizons)) if K > longest}
    horizons = sorted(K for K in set(horizons) if K <= longest)
    if not horizons:
        raise ValueError(f"no horizon fits trajectories of {longest + 1 + start} frames from t0 = {start}")
    if dropped:
        log.warning("inverse horizons K = %s dropped: %s", ", ".join(map(str, dropped)), next(iter(dropped.values())))
    rows: dict[str, dict[int, list[dict]]] = {}
    budget: dict[str, list[dict]] = {}

    for index, (position, particle_type) in enumerate(trajectories):
        moving = particle_type != KINEMATIC
        for label, model in feed_forward.items():
            feed_forward_inverse(model, State.from_positions(position[start - history: start + 1], particle_type), 1)
            for K in horizons:  # (after one untimed warm-up step)
                state = State.from_positions(position[start + K - history: start + K + 1], particle_type)
                result, _ = feed_forward_inverse(model, state, K)
                resimulated = model.rollout(State(result.initial_position, result.initial_velocity, particle_type), K)
                rows.setdefault(label, {}).setdefault(K, []).append(dict(
                    seconds=result.seconds, status="feed_forward",
                    consistency_mse=_mse(resimulated[-1][moving], position[start + K][moving]),
                    inverse_mse=_mse(result.initial_position[moving], position[start][moving])))
        for kind, options in optimisers.items():
            simulator, label = _optimiser_simulator(kind, options, metadata, models, position.shape[1], particle_type)
            solve = {k: options[k] for k in ("lr", "velocity_lr", "clip", "schedule") if k in options}
            target_velocity = position[start + 1] - position[start]
            init_velocity = (State.from_positions(position[start - history: start + 1], particle_type).velocity_history
                             if kind == "learned" else target_velocity)
            _warm_up(simulator, position[start], init_velocity)
            for K in horizons:
                if "horizons" in options and K not in options["horizons"]:
                    continue
                target = State.from_positions(position[start + K - history: start + K + 1], particle_type)
                init = target.velocity_history if kind == "learned" else target.velocity_history[:, -1]
                result = optimise_initial_state(simulator, target.position, K, init_position=target.position,
                                                init_velocity=init, target_velocity=target.velocity_history[:, -1],
                                                rule=stopping, mask=moving, **solve)
                resimulated = simulator.trajectory(result.initial_position, result.initial_velocity, K)
                row = dict(result.summary(), consistency_mse=_mse(resimulated[-1][moving], position[start + K][moving]),
                           inverse_mse=_mse(result.initial_position[moving], position[start][moving]))
                rows.setdefault(label, {}).setdefault(K, []).append(row)
                log.info("trajectory %d, K=%d, %s: %s (%s), %.2f s, consistency %s", index, K, label, row["status"],
                         row["reason"], row["seconds"], row["consistency_mse"])

        if budget_iterations:  # the cost of trying: a fixed number of iterations, failure checks off
            for kind, options in optimisers.items():
                K = max([k for k in horizons if k <= table_horizon] or horizons[:1])
                simulator, label = _optimiser_simulator(kind, options, metadata, models, position.shape[1], particle_type)
                if "horizons" in options and K not in options["horizons"]:
                    continue
                solve = {k: options[k] for k in ("lr", "velocity_lr", "clip", "schedule") if k in options}
                target = State.from_positions(position[start + K - history: start + K + 1], particle_type)
                init = target.velocity_history if kind == "learned" else target.velocity_history[:, -1]
                _warm_up(simulator, position[start], init)
                budget_rule = StoppingRule(max_iterations=budget_iterations, abs_tol=0.0, rel_tol=-1.0,
                                           divergence_factor=math.inf, max_grad_norm=math.inf)
                result = optimise_initial_state(simulator, target.position, K, init_position=target.position,
                                                init_velocity=init, target_velocity=target.velocity_history[:, -1],
                                                rule=budget_rule, mask=moving, **solve)
                budget.setdefault(label, []).append(dict(
                    horizon=K, iterations=result.iterations, seconds=result.seconds, status=result.status,
                    reason=result.reason, seconds_per_iteration=result.seconds / max(result.iterations, 1),
                    best_loss=result.summary()["loss"]))
                log.info("budget run, trajectory %d, K=%d, %s: %d iterations in %.1f s", index, K, label,
                         result.iterations, result.seconds)

    methods = {label: _aggregate(per_k, threshold) for label, per_k in rows.items()}
    for label, model in models.items():
        if label in methods:
            methods[label]["parameters"] = count_parameters(model)
    table_horizon = max([K for K in horizons if K <= table_horizon] or horizons[:1])
    ratios = {}
    for slow, row in methods.items():
        for fast, fast_row in methods.items():
            if fast in feed_forward and slow not in feed_forward:
                a, b = row["horizons"].get(table_horizon), fast_row["horizons"].get(table_horizon)
                if a and b and a["seconds"] and b["seconds"]:
                    ratios[f"{slow} / {fast}"] = a["seconds"] / b["seconds"]
    budget_ratios = {}
    for slow, runs in budget.items():
        seconds = float(np.mean([r["seconds"] for r in runs]))
        per_iteration = float(np.mean([r["seconds_per_iteration"] for r in runs]))
        done = min(r["iterations"] for r in runs)
        for fast in feed_forward:
            at = methods[fast]["horizons"].get(runs[0]["horizon"])
            if at and at["seconds"]:
                budget_ratios[f"{slow} ({done} of {budget_iterations} iterations ran) / {fast}"] = seconds / at["seconds"]
                budget_ratios[f"{slow}, one Adam iteration / {fast}"] = per_iteration / at["seconds"]
    results = dict(settings=dict(start=start, horizons=horizons, dropped_horizons=dropped, threshold=threshold,
                                 table_horizon=table_horizon,
                                 trajectories=len(trajectories), particles=[int(p.shape[1]) for p, _ in trajectories],
                                 rule=vars(stopping), optimisers=optimisers, threads=torch.get_num_threads()),
                   methods=methods, time_ratio_at_table_horizon=ratios)
    if budget:
        results["fixed_budget"] = dict(runs=budget, time_ratio=budget_ratios)
    if stability_steps:
        results["stability"] = long_rollout_stability(models, trajectories, start, stability_steps, divergence)
    if out_dir is not None:
        write_outputs(results, Path(out_dir))
    return results


def _aggregate(per_k: dict[int, list[dict]], threshold: float) -> dict:
    horizons = {}
    for K, runs in sorted(per_k.items()):
        consistency = [r["consistency_mse"] for r in runs]
        statuses = [r["status"] for r in runs]
        horizons[K] = dict(
            consistency_mse=None if None in consistency else float(np.mean(consistency)),
            inverse_mse=None if any(r["inverse_mse"] is None for r in runs) else float(np.mean([r["inverse_mse"] for r in runs])),
            seconds=float(np.mean([r["seconds"] for r in runs])),
            statuses=statuses,
            iterations=[r.get("iterations") for r in runs] if "iterations" in runs[0] else None,
            reasons=[r["reason"] for r in runs] if "reason" in runs[0] else None,
            stable=all(c is not None and c < threshold for c in consistency) and "failed" not in statuses)
    stable, beyond = 0, True
    for K, row in horizons.items():
        if not row["stable"]:
            beyond = False
            break
        stable = K
    return dict(horizons=horizons, max_stable_steps=stable, stable_beyond_tested=beyond)


def long_rollout_stability(models: dict, trajectories, start: int, steps: int, divergence: dict | None = None) -> dict:
    """Per model: forward from t0 and inverse from the last frame, ``steps`` long, on the first trajectory."""
    position, particle_type = trajectories[0]
    settings = dict(divergence or {})
    out = {}
    for label, model in models.items():
        row = dict(forward=forward_stability(model, position, particle_type, start, steps, **settings))
        if model.bidirectional:
            row["inverse"] = inverse_stability(model, position, particle_type, len(position) - 1, steps, **settings)
        out[label] = row
    return out


def add_out_arguments(parser: argparse.ArgumentParser) -> None:
    """``--out DIR`` (required) and ``--overwrite``, for :func:`refuse_earlier_out`."""
    parser.add_argument("--out", required=True)
    parser.add_argument("--overwrite", action="store_true", help="write into an --out folder that holds files already")


def refuse_earlier_out(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Exit 2 (``parser.error``) when ``--out`` holds files and ``--overwrite`` was not given."""
    out = Path(args.out)
    if out.is_dir() and any(out.iterdir()) and not args.overwrite:
        parser.error(f"--out {args.out}: holds files already (an earlier run's results?); refused, so as not to write "
                     "over them. Choose another folder, or add --overwrite")


def write_outputs(results: dict, out_dir: Path) -> None:
    """``inverse_comparison.json``, ``inverse_comparison.md`` (the table at the table horizon and the K
    sweep) and ``inverse_k_sweep.png`` (consistency MSE and seconds against K, per method)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    write_whole(out_dir / "inverse_comparison.json", (json.dumps(results, indent=2, default=str) + "\n").encode())
    write_whole(out_dir / "inverse_comparison.md", markdown(results).encode())
    k_sweep_chart(results, out_dir / "inverse_k_sweep.png")


def _fmt(value, spec: str = ".3g") -> str:
    return "-" if value is None else format(value, spec)


def markdown(results: dict) -> str:
    s = results["settings"]
    K = s["table_horizon"]
    lines = [f"## Inverse comparison at K = {K}", "",
             f"t0 = {s['start']}, {s['trajectories']} trajectories ({s['particles']} particles), "
             f"stable: consistency MSE < {s['threshold']:g} and not failed.", "",
             "| method | consistency MSE | inverse MSE | time (s) | parameters | status | max stable steps |",
             "|---|---|---|---|---|---|---|"]
    for label, row in results["methods"].items():
        at = row["horizons"].get(K) or row["horizons"].get(str(K)) or {}
        stable = f"{row['max_stable_steps']}" + ("+" if row["stable_beyond_tested"] else "")
        lines.append(f"| {label} | {_fmt(at.get('consistency_mse'))} | {_fmt(at.get('inverse_mse'))} | "
                     f"{_fmt(at.get('seconds'), '.4g')} | {row.get('parameters', '-')} | "
                     f"{', '.join(at.get('statuses') or []) or '-'} | {stable} |")
    for name, ratio in results.get("time_ratio_at_table_horizon", {}).items():
        lines.append(f"\nTime ratio at K = {K} (optimiser run to the stopping rule), {name}: **{ratio:.0f}x**")
    for name, ratio in results.get("fixed_budget", {}).get("time_ratio", {}).items():
        lines.append(f"\nTime ratio at K = {K}, fixed budget, {name}: **{ratio:.0f}x**")
    lines += ["", "## Horizon sweep (consistency MSE; seconds)", "",
              "| method | " + " | ".join(f"K={k}" for k in s["horizons"]) + " |",
              "|---|" + "---|" * len(s["horizons"])]
    for label, row in results["methods"].items():
        cells = []
        for k in s["horizons"]:
            at = row["horizons"].get(k) or row["horizons"].get(str(k))
            cells.append("-" if at is None else f"{_fmt(at['consistency_mse'])}; {_fmt(at['seconds'], '.3g')} s"
                         + ("" if at["stable"] else " (unstable)"))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if "stability" in results:
        lines += ["", "## Long rollouts: stable for n steps", "", "| method | forward | inverse |", "|---|---|---|"]
        for label, row in results["stability"].items():
            def show(r):
                return "-" if r is None else f"{r['stable_steps']} of {r['steps']}" + ("" if r["diverged"] else " (never broke)")
            lines.append(f"| {label} | {show(row['forward'])} | {show(row.get('inverse'))} |")
    return "\n".join(lines) + "\n"


def k_sweep_chart(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    threshold = results["settings"]["threshold"]
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    for i, (label, row) in enumerate(results["methods"].items()):
        ks = sorted(int(k) for k in row["horizons"])
        at = [row["horizons"].get(k) or row["horizons"][str(k)] for k in ks]
        consistency = [np.nan if a["consistency_mse"] is None else a["consistency_mse"] for a in at]
        line, = left.plot(ks, consistency, marker="o", label=label)
        failed = [k for k, a in zip(ks, at) if not a["stable"]]
        left.scatter(failed, [c for k, c in zip(ks, consistency) if k in failed], marker="x", s=80, color=line.get_color())
        if row["max_stable_steps"]:
            left.axvline(row["max_stable_steps"], color=line.get_color(), linestyle=":", alpha=0.6)
        right.plot(ks, [a["seconds"] for a in at], marker="o", color=line.get_color(), label=label)
    left.axhline(threshold, color="grey", linestyle="--", linewidth=1, label=f"threshold {threshold:g}")
    left.set(xlabel="inverse steps K", ylabel="consistency MSE", yscale="log",
             title="consistency vs K (x: unstable; dotted: max stable K)")
    right.set(xlabel="inverse steps K", ylabel="inverse inference time (s)", yscale="log", title="time vs K")
    left.legend(fontsize=8)
    right.legend(fontsize=8)
    save_figure(fig, path)


def run_inverse_comparison(models: dict, dataset_root: str | Path, horizons, out_dir: str | Path,
                           split: str = "test", trajectories: int | None = 1, **settings) -> dict:
    """:func:`compare_inverse` on the first ``trajectories`` of a dataset folder's ``split``."""
    metadata = read_metadata(dataset_root)
    with open_split(dataset_root, split) as data:
        count = len(data) if trajectories is None else min(trajectories, len(data))
        loaded = [(torch.from_numpy(p), torch.from_numpy(t)) for p, t in (data[i] for i in range(count))]
    return compare_inverse(models, metadata, loaded, horizons, out_dir=out_dir, **settings)


class InverseComparison:
    """The comparison as an ``evaluate.py`` task (``task(methods, dataset) -> (results, examples)``).

    Args: as :func:`compare_inverse`, plus ``out_dir`` (the run folder) and ``trajectories`` (the
    first n of the evaluation's, default 1: optimisation is slow); ``optimisers``: ``None`` runs
    none, a kind set to ``None`` is left out (:func:`chosen_optimisers`).
    """

    name = "inverse_optimisation"

    def __init__(self, out_dir: str, horizons=(1, 5, 10, 20, 40), trajectories: int = 1, **settings):
        if "optimisers" in settings:  # null: none; a kind set to null: left out (chosen_optimisers)
            settings["optimisers"] = chosen_optimisers(settings["optimisers"])
        self.out_dir, self.horizons, self.trajectories, self.settings = out_dir, list(horizons), trajectories, settings

    def __call__(self, methods, dataset) -> tuple[dict, dict]:
        models = {m.label: m.model for m in methods}
        out = Path(self.out_dir) / f"inverse_{dataset.name}"
        results = compare_inverse(models, dataset.metadata, dataset.trajectories[: self.trajectories], self.horizons,
                                  start=dataset.start, out_dir=out, **self.settings)
        return json.loads(json.dumps(results, default=str)), {}


def main(argv: list[str] | None = None) -> dict:
    """``python -m rgns.inverse.tasks --ckpt A.ckpt [--ckpt B.ckpt] --out DIR [--horizons 1 5 10 20 40]``"""
    from rgns.evaluation.methods import check_fits, trained_on
    from rgns.training.module import load_simulator

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", action="append", required=True)
    parser.add_argument("--label", action="append", help="a label per --ckpt (default: the model class)")
    parser.add_argument("--data-root")
    parser.add_argument("--split", default="test", choices=SPLITS)
    parser.add_argument("--trajectories", type=int, default=1)
    parser.add_argument("--horizons", type=int, nargs="+", default=[1, 5, 10, 20, 40],
                        help="the K tried; each must fit the trajectories (a longer one is refused)")
    parser.add_argument("--optimisers", nargs="*", default=["sph"],
                        help="sph, mpm, learned (through the first model); kind:K,K to run only those horizons")
    parser.add_argument("--iterations", type=int, default=50, help="the stopping rule's iteration cap")
    parser.add_argument("--threshold", type=float, default=1e-3)
    parser.add_argument("--stability-steps", type=int, default=1000)
    parser.add_argument("--budget-iterations", type=int, default=0,
                        help="also time each optimiser for exactly this many iterations at the table horizon")
    add_out_arguments(parser)
    args = parser.parse_args(argv)
    refuse_earlier_out(parser, args)
    if args.label and len(args.label) != len(args.ckpt):
        parser.error(f"{len(args.label)} --label for {len(args.ckpt)} --ckpt: give one label per checkpoint, or none")
    if min(args.horizons) < 1 or args.trajectories < 1 or args.iterations < 1:
        parser.error(f"--horizons {' '.join(map(str, args.horizons))}, --trajectories {args.trajectories} and "
                     f"--iterations {args.iterations}: each must be at least 1")
    if args.threshold <= 0 or args.stability_steps < 0 or args.budget_iterations < 0:
        parser.error("--threshold must be > 0, --stability-steps and --budget-iterations >= 0")
    optimisers = {}
    for item in args.optimisers:  # kind or kind:K,K,... (only those horizons, e.g. mpm:1,5)
        kind, _, ks = item.partition(":")
        if kind not in ("sph", "mpm", "learned"):
            parser.error(f"--optimisers {item}: the kinds are sph, mpm and learned (kind:K,K runs only those K)")
        try:
            optimisers[kind] = {"horizons": [int(k) for k in ks.split(",")]} if ks else {}
        except ValueError:
            parser.error(f"--optimisers {item}: after '{kind}:' come horizons K separated by commas, e.g. {kind}:1,5")
        unasked = sorted(set(optimisers[kind].get("horizons", [])) - set(args.horizons))
        if unasked:
            parser.error(f"--optimisers {item}: K = {unasked} not among --horizons {' '.join(map(str, args.horizons))}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(1)
    names = {"RGNS": "R-GNS", "SepGNS": "Sep-GNS", "GNS": "GNS"}
    models, root = {}, args.data_root
    for i, path in enumerate(args.ckpt):
        model, extras = load_simulator(path)
        label = args.label[i] if args.label else names.get(type(model).__name__, type(model).__name__)
        if label in models:
            parser.error(f"--ckpt {path}: a second checkpoint labelled {label!r}; give each one a --label")
        models[label] = model
        root = root or trained_on(path, extras["data_root"], extras["data_root_relative"])
    if root is None:
        parser.error("the checkpoint does not name its dataset: pass --data-root")
    history = next(iter(models.values())).history  # t0 = k, as compare_inverse
    contents = check_dataset(root, min_frames=history + 2, splits=(args.split,))
    where = Path(root) / f"{args.split}.h5"
    for path, model in zip(args.ckpt, models.values()):
        check_fits(model, path, contents.metadata, contents.particle_types[args.split], str(where))
    if not contents.shapes[args.split]:
        raise DatasetError(f"{where}: no trajectories to compare on")
    frames = min(shape[0] for shape in contents.shapes[args.split][: args.trajectories])
    too_long = [K for K in args.horizons if K > frames - 1 - history]
    if too_long:  # asked for by name: refused, not dropped
        parser.error(f"--horizons {' '.join(map(str, too_long))}: the first {args.trajectories} {args.split} "
                     f"trajectories of {root} have {frames} frames, so from t0 = k = {history} the longest "
                     f"horizon is {frames - 1 - history}")
    results = run_inverse_comparison(models, root, args.horizons, args.out, split=args.split,
                                     trajectories=args.trajectories, optimisers=optimisers,
                                     rule=dict(max_iterations=args.iterations), threshold=args.threshold,
                                     stability_steps=args.stability_steps, budget_iterations=args.budget_iterations)
    print(markdown(results))
    return results


if __name__ == "__main__":
    main()
