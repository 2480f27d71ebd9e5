"""Model no more than a scene needs: ``python -m rgns.bench sizes RESULTS [RESULTS ...]
[--factor 1.5] [--dataset NAME] [--json PATH]``.

Reads evaluations (``results.json`` files written by ``evaluate.py``, or folders holding them,
searched recursively) of trained models of several sizes, groups their runs by size (the
checkpoint's model configuration as ``rgns.evaluation.methods.describe`` names it: model, latent
x layers, variant; runs that also differ in other training overrides than the seed are kept
apart, the differing overrides added to the name) and prints, per dataset and size: parameters,
rollout MSE mean ± standard deviation over the runs (seeds; n - 1 in the deviation), and ms per
frame (the evaluation's efficiency task, mean over the runs). It names the best mean and the
smallest size (fewest parameters) whose mean is at most ``--factor`` times the best: the model
the scene needs. A size with a run whose rollout MSE is missing or not finite (a diverged
rollout) is shown but never picked. The training-free baselines, the solver references and the
twins rolled out without hard walls are left out; a checkpoint evaluated in several files counts
once (its first).

Runs trained on every k-th frame (``data.stride``, the evaluation's ``stride``) are sizes of their
own, named ``stride k``; their ``data.stride`` and validation lengths (scaled with the stride) are
not counted as another recipe. ``--metric rollout_mse_shared`` compares them on the frames every
method predicts itself (docs/metrics.md, "Strided methods"), which with stride-1 runs alone is the
rollout MSE; ms per frame is a step's time over the frames it covers.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
from pathlib import Path

from rgns.evaluation.methods import describe
from rgns.evaluation.plots import write_whole

# training overrides that do not make another model: the seed, the size itself, and paths of one run
NOT_A_RECIPE = ("seed=", "model.latent=", "model.layers=", "init_from=", "resume=", "hydra.")
# a strided run's stride and the validation lengths scaled with it: named by "stride k" instead
STRIDE_OVERRIDES = ("data.stride=", "module.val_rollout_steps=", "module.val_consistency_steps=")
METRICS = ("rollout_mse", "rollout_mse_shared")


def read_results(paths: list[str | Path]) -> list[tuple[Path, dict]]:
    """``(file, results)`` of every ``results.json`` given, or found under a folder given."""
    files = []
    for path in map(Path, paths):
        if path.is_dir():
            found = sorted(path.rglob("results.json"))
            if not found:
                raise FileNotFoundError(f"{path}: no results.json under this folder (evaluate.py writes one)")
            files += found
        elif path.is_file():
            files.append(path)
        else:
            raise FileNotFoundError(f"{path}: no such file or folder")
    out = []
    for file in dict.fromkeys(files):
        try:
            results = json.loads(file.read_text())
        except json.JSONDecodeError as error:
            raise ValueError(f"{file}: not a results.json ({error})") from None
        if not isinstance(results, dict) or "methods" not in results or "datasets" not in results:
            raise ValueError(f"{file}: not an evaluate.py results.json (no 'methods' and 'datasets')")
        out.append((file, results))
    return out


def _parameters(row: dict, source: str) -> int | None:
    """The parameter count of the evaluation, else of the checkpoint where it can be read."""
    if row.get("parameters") is not None:
        return int(row["parameters"])
    if not Path(source).is_file():
        return None
    from rgns.models import count_parameters
    from rgns.training.module import load_simulator

    return count_parameters(load_simulator(source)[0])


def trained_runs(results: list[tuple[Path, dict]], dataset: str | None = None,
                 metric: str = "rollout_mse") -> list[dict]:
    """One row per trained checkpoint scored on a dataset: its size, stride, seed, rollout MSE
    (``metric``: ``rollout_mse`` or ``rollout_mse_shared``), parameters and ms per frame, and the
    training overrides that are not its size, stride or seed."""
    if metric not in METRICS:
        raise ValueError(f"metric {metric!r}: one of {', '.join(METRICS)}")
    runs, seen = [], set()
    for file, result in results:
        for name, sections in result["datasets"].items():
            if dataset is not None and name != dataset:
                continue
            for label, row in sections.get("summary", {}).items():
                info = result["methods"].get(label, {})
                if "model" not in info or info.get("hard_walls") is False:  # baselines, references, twins
                    continue
                key = (name, info["source"])
                if key in seen:
                    continue
                seen.add(key)
                model = info["model"]
                mse = row.get(metric)
                stride = int(row.get("stride") or 1)
                ignored = NOT_A_RECIPE + (STRIDE_OVERRIDES if stride > 1 else ())
                runs.append(dict(
                    dataset=name, label=label, source=info["source"], results=str(file),
                    size=describe(model) + (f" stride {stride}" if stride > 1 else "")
                    + (" pretrained" if info.get("pretrained") else ""),
                    latent=model.get("latent"), layers=model.get("layers"), stride=stride, seed=info.get("seed"),
                    rollout_mse=float(mse) if mse is not None else None,
                    ms_per_frame=row.get("forward_ms_per_frame"), parameters=_parameters(row, info["source"]),
                    recipe=tuple(sorted(o for o in info.get("overrides", []) if not o.startswith(ignored)))))
    if not runs:
        where = f" on dataset {dataset}" if dataset else ""
        raise ValueError(f"{', '.join(str(f) for f, _ in results)}: no trained model's rollout MSE{where} "
                         "(evaluate the checkpoints with task=forward or task=all)")
    return runs


def group(runs: list[dict]) -> list[dict]:
    """Runs of one dataset, size and recipe together: ``{dataset, name, latent, layers, parameters,
    n, seeds, mean, std, ms_per_frame, complete}``, sorted by dataset and parameters."""
    recipes = {r["recipe"] for r in runs}
    common = set.intersection(*(set(r) for r in recipes))
    groups: dict[tuple, list[dict]] = {}
    for run in runs:
        groups.setdefault((run["dataset"], run["size"], run["recipe"]), []).append(run)
    out = []
    for (dataset, size, recipe), members in groups.items():
        own = [o for o in recipe if o not in common]
        values = [r["rollout_mse"] for r in members]
        complete = all(v is not None and math.isfinite(v) for v in values)
        finite = [v for v in values if v is not None and math.isfinite(v)]
        times = [r["ms_per_frame"] for r in members if r["ms_per_frame"] is not None]
        counts = {r["parameters"] for r in members}
        if len(counts) > 1:
            raise ValueError(f"{size}: runs of one size with different parameter counts {sorted(counts, key=str)} "
                             f"({', '.join(r['source'] for r in members)})")
        out.append(dict(dataset=dataset, name=size + (f" ({','.join(own)})" if own else ""),
                        latent=members[0]["latent"], layers=members[0]["layers"], stride=members[0]["stride"],
                        parameters=counts.pop(),
                        n=len(members), seeds=[r["seed"] for r in members], values=values,
                        mean=statistics.fmean(finite) if finite else None,
                        std=statistics.stdev(finite) if len(finite) > 1 else None,
                        ms_per_frame=statistics.fmean(times) if times else None, complete=complete))
    return sorted(out, key=lambda g: (g["dataset"], g["parameters"] is None, g["parameters"] or 0, g["stride"], g["name"]))


def pick(groups: list[dict], factor: float) -> tuple[dict | None, dict | None]:
    """The size of best mean rollout MSE and the smallest (parameters) within ``factor`` of it,
    among the sizes whose every run has a finite rollout MSE and whose parameters are known."""
    eligible = [g for g in groups if g["complete"] and g["mean"] is not None and g["parameters"] is not None]
    if not eligible:
        return None, None
    best = min(eligible, key=lambda g: g["mean"])
    within = [g for g in eligible if g["mean"] <= factor * best["mean"]]
    return best, min(within, key=lambda g: (g["parameters"], g["mean"]))


def table(groups: list[dict], factor: float) -> str:
    """Per dataset: a row per size and the two picks."""
    lines = []
    for dataset in dict.fromkeys(g["dataset"] for g in groups):
        mine = [g for g in groups if g["dataset"] == dataset]
        best, smallest = pick(mine, factor)
        lines += [f"dataset {dataset}: {len(mine)} sizes, {sum(g['n'] for g in mine)} runs", "",
                  "| model | latent x layers | parameters | rollout MSE mean ± std (n) | / best | ms per frame |",
                  "|---|---|---|---|---|---|"]
        for g in mine:
            spread = f" ± {g['std']:.3g}" if g["std"] is not None else ""
            failed = "" if g["complete"] else f", {sum(1 for v in g['values'] if v is None or not math.isfinite(v))} not finite"
            mse = "-" if g["mean"] is None else f"{g['mean']:.3g}{spread} ({g['n']}{failed})"
            ratio = "-" if g["mean"] is None or best is None else f"{g['mean'] / best['mean']:.2f}"
            ms = "-" if g["ms_per_frame"] is None else f"{g['ms_per_frame']:.1f}"
            params = "-" if g["parameters"] is None else f"{g['parameters']:,}"
            lines.append(f"| {g['name']} | {g['latent']}x{g['layers']} | {params} | {mse} | {ratio} | {ms} |")
        lines.append("")
        if best is None:
            lines.append("no size has a finite rollout MSE in every run and a known parameter count: none picked")
        else:
            lines.append(f"best mean rollout MSE: {best['name']}, {best['mean']:.3g} over {best['n']} run(s)")
            lines.append(f"smallest within {factor:g}x of the best: {smallest['name']} ({smallest['parameters']:,} "
                         f"parameters, rollout MSE {smallest['mean']:.3g}, {smallest['mean'] / best['mean']:.2f}x the "
                         f"best, over {smallest['n']} run(s))")
        lines.append("")
    return "\n".join(lines).rstrip()


def main(argv: list[str]) -> dict:
    parser = argparse.ArgumentParser(prog="python -m rgns.bench sizes", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", help="results.json files or folders holding them")
    parser.add_argument("--factor", type=float, default=1.5, help="how far from the best mean a size may be")
    parser.add_argument("--dataset", default=None, help="only this dataset of the evaluations (default: each)")
    parser.add_argument("--metric", choices=METRICS, default="rollout_mse",
                        help="rollout_mse_shared: on the frames every method predicts itself (strided runs)")
    parser.add_argument("--json", type=Path, help="write the sizes and the picks here")
    args = parser.parse_args(argv)
    if args.factor < 1:
        parser.error(f"--factor {args.factor}: at least 1 (1: the best size itself)")
    groups = group(trained_runs(read_results(args.results), args.dataset, args.metric))
    print(f"metric: {args.metric}")
    print(table(groups, args.factor))
    picks = {}
    for dataset in dict.fromkeys(g["dataset"] for g in groups):
        best, smallest = pick([g for g in groups if g["dataset"] == dataset], args.factor)
        picks[dataset] = dict(best=best and best["name"], smallest_within_factor=smallest and smallest["name"])
    out = dict(factor=args.factor, metric=args.metric, sizes=groups, picks=picks)
    if args.json:
        write_whole(args.json, (json.dumps(out, indent=2) + "\n").encode())
    return out
