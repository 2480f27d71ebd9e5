"""Accuracy against cost, learned models and the dataset's solver side by side:
``python -m rgns.bench front [--checkpoints A B ...] [--data-root DIR] [--trajectories N] [--steps S]
[--resolutions F ...] [--reference CKPT] [--within F] [--precision P ...] [--json PATH]``.

Every method rolls out the same test trajectories of one dataset in one process on one thread,
in turns (trajectory by trajectory, every method on each before the next), so that a drift in the
machine's speed reaches them all alike:

- the checkpoints (default: the shipped ``pretrained/waterdrop40_main*/*.ckpt``), each timed over
  its whole rollout, radius graphs included: ms per frame is the rollout's wall time over its
  frames (a model that steps over several frames, ``data.stride``, covers them in one step);
- the dataset's own solver re-run from the same initial states at ``--resolutions`` of its
  stored grid (:mod:`rgns.evaluation.references`) and at the stored grid from perturbed
  positions (the predictability floor), each timed over its own rollout (Taichi's compilation
  excluded).

Rollout MSE is the evaluation's: the mean over steps and particles of the squared position
error, averaged over the trajectories. Printed: one row per method, the two fronts (the methods
that no cheaper one of their kind beats), each learned model's cost against the solver's at the
same accuracy (interpolated log-log along the solver's front; beyond its ends a bound), and the
issue's two marks: the fastest learned model at most the half-resolution solver's error against
``--reference`` (the shipped R-GNS by default), and whether any learned model sits on the
solver's front (at most the half-resolution solver's error in at most its time per frame); and the
model a scene needs: the smallest learned model (parameters) within ``--within`` times the best
learned rollout MSE (pass a size sweep's checkpoints).
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os
import time
from pathlib import Path

import torch

from rgns.evaluation.metrics import mse_per_step
from rgns.evaluation.methods import find_checkpoints, load_checkpoints
from rgns.evaluation.plots import pareto_front, write_whole
from rgns.evaluation.references import SolverReferences
from rgns.evaluation.tasks import Dataset

DEFAULT_CHECKPOINTS = "pretrained/waterdrop40_main*/*.ckpt"


def cost_at(solver_front: list[tuple[float, float, str]], mse: float) -> tuple[str, float]:
    """The solver's ms per frame at rollout MSE ``mse``, read off its front of ``(ms, mse, label)``
    (log-log between the two points that bracket it): ``("=", ms)``; beyond the front's most
    accurate point ``(">", its ms)`` (finer than measured); beyond its cheapest ``("<", its ms)``."""
    if not solver_front:
        raise ValueError("no solver points: the dataset has no solver references")
    (cheap_ms, cheap_mse, _), (fine_ms, fine_mse, _) = solver_front[0], solver_front[-1]
    if mse >= cheap_mse:
        return ("=", cheap_ms) if mse == cheap_mse else ("<", cheap_ms)
    if mse < fine_mse:
        return (">", fine_ms)
    for (ms_a, mse_a, _), (ms_b, mse_b, _) in zip(solver_front, solver_front[1:]):
        if mse_b <= mse <= mse_a:
            weight = (math.log(mse_a) - math.log(mse)) / (math.log(mse_a) - math.log(mse_b))
            return ("=", math.exp(math.log(ms_a) + weight * (math.log(ms_b) - math.log(ms_a))))
    raise AssertionError("unreachable: a front's mse falls strictly from its cheapest point")


def measure(methods: list, dataset: Dataset, steps: int, log=print) -> dict[str, dict]:
    """Rollout MSE and ms per frame of every method on every trajectory, in turns."""
    seconds = {m.label: 0.0 for m in methods}
    frames = {m.label: 0 for m in methods}
    errors = {m.label: [] for m in methods}
    for i, (position, _) in enumerate(dataset.trajectories):
        length = min(steps, len(position) - 1 - dataset.start)
        truth = position[dataset.start + 1 : dataset.start + 1 + length]
        for method in methods:
            if method.model is None:  # a solver reference: its own timing of its rollout, compilation excluded
                predicted = method.forward_rollout(dataset, i, length)
                seconds[method.label] += method.ms_per_frame(i) / 1e3 * length
            else:
                begin = time.perf_counter()
                predicted = method.forward_rollout(dataset, i, length)
                seconds[method.label] += time.perf_counter() - begin
            frames[method.label] += length
            errors[method.label].append(float(mse_per_step(predicted, truth).mean()))
        log(f"trajectory {i + 1}/{len(dataset.trajectories)} done", flush=True)
    return {m.label: dict(rollout_mse=sum(errors[m.label]) / len(errors[m.label]),
                          ms_per_frame=1e3 * seconds[m.label] / frames[m.label],
                          learned=m.model is not None, parameters=m.parameters if m.model is not None else 0,
                          source=m.source if m.model is not None else "solver",
                          settings=getattr(m, "settings", None))
            for m in methods}


def analyse(rows: dict[str, dict], reference: str | None, within: float = 1.5) -> dict:
    """The fronts, each learned model against the solver at its accuracy, the two marks, and the
    smallest learned model (parameters, then ms per frame) within ``within`` times the best
    learned rollout MSE: the model a scene needs."""
    learned = [(r["ms_per_frame"], r["rollout_mse"], k) for k, r in rows.items() if r["learned"]]
    solvers = [(r["ms_per_frame"], r["rollout_mse"], k) for k, r in rows.items() if not r["learned"]]
    solver_front, learned_front = pareto_front(solvers), pareto_front(learned)
    against = {}
    for ms, mse, label in learned:
        relation, solver_ms = cost_at(solver_front, mse)
        against[label] = dict(solver_ms_at_same_mse=solver_ms, relation=relation, ratio=ms / solver_ms)
    half = [k for k, r in rows.items() if not r["learned"] and (r["settings"] or {}).get("perturbation") is None
            and (r["settings"] or {}).get("n_grid") and r["settings"].get("stored_n_grid")
            and 2 * r["settings"]["n_grid"] == r["settings"]["stored_n_grid"]]
    marks = {}
    if half:
        bar = rows[half[0]]
        good = [(k, ms) for ms, mse, k in learned if mse <= bar["rollout_mse"]]
        fastest = min(good, key=lambda p: p[1]) if good else None
        marks = dict(half_resolution=half[0], half_resolution_mse=bar["rollout_mse"],
                     half_resolution_ms_per_frame=bar["ms_per_frame"],
                     fastest_at_most_half_resolution_mse=None if fastest is None else fastest[0],
                     on_solver_front=[k for k, ms in good if ms <= bar["ms_per_frame"]])
        if fastest is not None and reference in rows:
            marks["reference"] = reference
            marks["reference_over_fastest"] = rows[reference]["ms_per_frame"] / fastest[1]
    best = min((mse for _, mse, _ in learned), default=None)
    close = [k for _, mse, k in learned if mse <= within * best] if best is not None else []
    smallest = min(close, key=lambda k: (rows[k].get("parameters") or 0, rows[k]["ms_per_frame"]), default=None)
    return dict(solver_front=[p[2] for p in solver_front], learned_front=[p[2] for p in learned_front],
                against_solver=against, marks=marks, within=within, smallest_within=smallest)


def report(rows: dict[str, dict], analysis: dict) -> str:
    """The printed table and the marks."""
    width = max(len(k) for k in rows) + 2
    lines = [f"{'method':<{width}} {'rollout MSE':>12} {'ms/frame':>9}  front   solver ms/frame at its MSE (ratio)"]
    for label, row in sorted(rows.items(), key=lambda kv: kv[1]["ms_per_frame"]):
        on = ("solver" if label in analysis["solver_front"] else
              "learned" if label in analysis["learned_front"] else "")
        line = f"{label:<{width}} {row['rollout_mse']:>12.4e} {row['ms_per_frame']:>9.2f}  {on:<7}"
        if label in analysis["against_solver"]:
            a = analysis["against_solver"][label]
            relation = {"=": "", ">": "more than ", "<": "less than "}[a["relation"]]
            ratio = {"=": "", ">": "at most ", "<": "at least "}[a["relation"]]
            line += f" {relation}{a['solver_ms_at_same_mse']:.2f} ({ratio}{a['ratio']:.1f}x the solver's time)"
        lines.append(line)
    if analysis.get("smallest_within"):
        k = analysis["smallest_within"]
        lines.append(f"smallest learned model within {analysis['within']:g}x of the best learned rollout MSE: {k} "
                     f"({rows[k].get('parameters') or 0:,} parameters, {rows[k]['ms_per_frame']:.2f} ms/frame)")
    marks = analysis["marks"]
    if not marks:
        lines.append("no half-resolution solver reference: the marks need one")
        return "\n".join(lines)
    lines.append(f"half-resolution solver: {marks['half_resolution']}, rollout MSE {marks['half_resolution_mse']:.4e}, "
                 f"{marks['half_resolution_ms_per_frame']:.2f} ms/frame")
    fastest = marks["fastest_at_most_half_resolution_mse"]
    if fastest is None:
        lines.append("no learned model is at most the half-resolution solver's rollout MSE")
    else:
        line = f"fastest learned model at most its rollout MSE: {fastest}, {rows[fastest]['ms_per_frame']:.2f} ms/frame"
        if "reference" in marks:
            line += (f"; {marks['reference']} takes {rows[marks['reference']]['ms_per_frame']:.2f} ms/frame: "
                     f"{marks['reference_over_fastest']:.2f}x the fastest's time")
        lines.append(line)
    on = marks["on_solver_front"]
    lines.append("on the solver's front (at most its error in at most its time per frame): "
                 + (", ".join(on) if on else "no learned model"))
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoints", nargs="+", default=None,
                        help=f"checkpoint files (default: {DEFAULT_CHECKPOINTS})")
    parser.add_argument("--data-root", default="datasets/waterdrop40_main", help="a generated dataset folder")
    parser.add_argument("--trajectories", type=int, default=8, help="the first N test trajectories")
    parser.add_argument("--steps", type=int, default=300, help="rollout steps (frames) from the start frame")
    parser.add_argument("--start", type=int, default=None, help="the first frame (default: the longest history)")
    parser.add_argument("--resolutions", type=float, nargs="+", default=[0.25, 0.375, 0.5, 0.75],
                        help="solver grids as fractions of the stored one")
    parser.add_argument("--floor", type=float, default=1e-4, help="the floor's perturbation, m (0: no floor)")
    parser.add_argument("--reference", default="pretrained/waterdrop40_main_64/rgns.ckpt",
                        help="the checkpoint the fastest good model is compared with")
    parser.add_argument("--within", type=float, default=1.5,
                        help="report the smallest model within this factor of the best learned rollout MSE")
    parser.add_argument("--precision", nargs="+", default=["float32"], choices=["float32", "bfloat16"],
                        help="each checkpoint at each of these (bfloat16: its matrix products; labelled 'bf16')")
    parser.add_argument("--json", default=None, help="also write the rows and the analysis here")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")

    paths = args.checkpoints if args.checkpoints is not None else sorted(glob.glob(DEFAULT_CHECKPOINTS))
    if not paths:
        parser.error(f"no checkpoints: pass --checkpoints ({DEFAULT_CHECKPOINTS} matches nothing here)")
    methods = []
    for precision in args.precision:  # each checkpoint at each arithmetic: "<label> bf16" for bfloat16
        loaded = load_checkpoints(find_checkpoints(ckpt_paths=paths))
        for method in loaded:
            method.model.precision = precision
            method.model.low_precision()  # refuses an unknown precision by name
            if precision != "float32":
                method.label += " bf16" if precision == "bfloat16" else f" {precision}"
        methods += loaded
    history = max(m.model.history * int((m.trained_metadata or {}).get("stride", 1)) for m in methods)
    dataset = Dataset.load(args.data_root, "test", args.trajectories, history, args.start)
    references, note = SolverReferences(args.resolutions, args.floor or None)(dataset)
    if not references:
        parser.error(f"{args.data_root}: {note}")
    reference = next((m.label for m in methods if Path(m.source).resolve() == Path(args.reference).resolve()
                      and m.model.precision == "float32"), None)
    print(f"{len(methods)} checkpoints and {len(references)} solver runs, {len(dataset.trajectories)} trajectories x "
          f"{args.steps} steps from frame {dataset.start}, one thread", flush=True)
    rows = measure(methods + references, dataset, args.steps)
    analysis = analyse(rows, reference, args.within)
    print(report(rows, analysis))
    if args.json:
        write_whole(args.json, json.dumps(dict(rows=rows, analysis=analysis, data_root=args.data_root,
                                               trajectories=len(dataset.trajectories), steps=args.steps,
                                               start=dataset.start), indent=2).encode())
