"""Is one simulator better than another on the same trajectories, or is it the draw of trajectories?

A split's rollout MSE is a mean over a few trajectories (8 on the default test split), and one
hard trajectory can carry half of it. This reads the per-trajectory rollout MSEs that
``evaluate.py`` wrote (``results.json``, forward task) for several methods, pairs each with a
reference method trajectory by trajectory, and reports the ratio of their means with a paired
bootstrap interval (the trajectories resampled with replacement, the same draw for both methods),
and on how many trajectories each is the lower::

    python -m rgns.evaluation.compare NAME=RESULTS[#LABEL][,RESULTS[#LABEL]...] ... \\
        [--reference NAME] [--resamples 10000] [--level 0.9] [--seed 0] [--json out.json]

``RESULTS`` is a ``results.json`` or the folder that holds it; ``LABEL`` the method's label in it,
needed only where the file holds several methods other than the training-free baselines. Several
``RESULTS`` for one name are pooled (e.g. the test split's run and the selection split's: their
trajectories side by side); every name must then cover the same datasets and splits with the same
number of trajectories, in any order. The reference is the first name unless ``--reference`` says
otherwise. An interval that holds 1 says the trajectories cannot tell the two apart.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np


class CompareError(ValueError):
    """An input that cannot be compared; the message names the file or the name and what is wrong."""


@dataclass(frozen=True)
class Scores:
    """One method's per-trajectory rollout MSEs, by dataset and split."""

    name: str
    parts: dict[tuple[str, str], np.ndarray]  # (dataset, split) -> [trajectories]

    def pooled(self, keys: list[tuple[str, str]]) -> np.ndarray:
        return np.concatenate([self.parts[key] for key in keys])


def _results_path(path: str) -> Path:
    p = Path(path)
    p = p / "results.json" if p.is_dir() else p
    if not p.is_file():
        raise CompareError(f"{path}: no results.json there (evaluate.py writes one to its run folder)")
    return p


def read_scores(name: str, spec: str) -> Scores:
    """The scores of ``NAME=RESULTS[#LABEL][,...]``'s right-hand side, ``spec``."""
    parts: dict[tuple[str, str], np.ndarray] = {}
    for item in spec.split(","):
        path, _, label = item.partition("#")
        file = _results_path(path)
        try:
            results = json.loads(file.read_text())
            datasets = results["datasets"]
        except (json.JSONDecodeError, KeyError, TypeError) as err:
            raise CompareError(f"{file}: not an evaluate.py results.json ({err!r})") from None
        baselines = {k for k, v in results.get("methods", {}).items() if v.get("source") == "baseline"}
        for dataset, section in datasets.items():
            methods = (section.get("forward") or {}).get("methods") or {}
            if not methods:
                raise CompareError(f"{file}: dataset {dataset} has no forward task's results")
            chosen = label or _only_trained(file, dataset, [m for m in methods if m not in baselines])
            if chosen not in methods:
                raise CompareError(f"{file}: no method {chosen!r} on {dataset}; it holds {sorted(methods)}")
            key = (dataset, str(section.get("split", "")))
            if key in parts:
                raise CompareError(f"{name}: {dataset} ({key[1]}) given twice")
            values = np.asarray(methods[chosen]["rollout_mse_per_trajectory"], dtype=float)
            if not np.all(np.isfinite(values)):
                raise CompareError(f"{file}: {chosen!r} on {dataset} has non-finite trajectory errors")
            parts[key] = values
    return Scores(name, parts)


def _only_trained(file: Path, dataset: str, labels: list[str]) -> str:
    if len(labels) != 1:
        raise CompareError(f"{file}: {dataset} holds {len(labels)} methods besides the baselines "
                           f"({labels}); name one as RESULTS#LABEL")
    return labels[0]


def paired_ratio(values: np.ndarray, reference: np.ndarray, resamples: int, level: float,
                 rng: np.random.Generator) -> tuple[float, float, float]:
    """``mean(values) / mean(reference)`` and its paired bootstrap interval at ``level``: both
    vectors resampled with the same indices. Shapes: ``[T]``, ``[T]``."""
    ratio = float(values.mean() / reference.mean())
    index = rng.integers(0, len(values), size=(resamples, len(values)))  # [B, T]
    draws = values[index].mean(1) / reference[index].mean(1)
    tail = (1 - level) / 2
    low, high = np.quantile(draws, [tail, 1 - tail])
    return ratio, float(low), float(high)


def compare(scores: list[Scores], reference: str, resamples: int = 10000, level: float = 0.9,
            seed: int = 0) -> list[dict]:
    """One row per name: its pooled mean, and against ``reference``'s the ratio of means, its
    paired bootstrap interval and the trajectories where each is lower."""
    by_name = {s.name: s for s in scores}
    if reference not in by_name:
        raise CompareError(f"--reference {reference}: not one of the names {list(by_name)}")
    keys = sorted(by_name[reference].parts)
    for s in scores:
        if sorted(s.parts) != keys:
            raise CompareError(f"{s.name} covers {sorted(s.parts)}, {reference} {keys}: compare like with like")
        for key in keys:
            if len(s.parts[key]) != len(by_name[reference].parts[key]):
                raise CompareError(f"{s.name} has {len(s.parts[key])} trajectories of {key[0]} ({key[1]}), "
                                   f"{reference} {len(by_name[reference].parts[key])}")
    base = by_name[reference].pooled(keys)
    rows = []
    for s in scores:
        values = s.pooled(keys)
        row = dict(name=s.name, trajectories=len(values), mean=float(values.mean()))
        if s.name != reference:
            rng = np.random.default_rng(seed)  # the same draws of trajectories for every name
            ratio, low, high = paired_ratio(values, base, resamples, level, rng)
            row.update(ratio=ratio, low=low, high=high, lower=int((values < base).sum()),
                       higher=int((values > base).sum()))
        rows.append(row)
    return rows


def render(rows: list[dict], reference: str, level: float) -> str:
    lines = [f"| name | trajectories | rollout MSE (1e-3) | ratio to {reference} | {level:.0%} interval "
             "| lower / higher |", "|---|---|---|---|---|---|"]
    for r in rows:
        if "ratio" in r:
            lines.append(f"| {r['name']} | {r['trajectories']} | {r['mean'] * 1e3:.4g} | {r['ratio']:.3f} "
                         f"| {r['low']:.3f}-{r['high']:.3f} | {r['lower']} / {r['higher']} |")
        else:
            lines.append(f"| {r['name']} (reference) | {r['trajectories']} | {r['mean'] * 1e3:.4g} | 1 | | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(prog="python -m rgns.evaluation.compare", description=__doc__.split("\n\n")[0])
    parser.add_argument("entries", nargs="+", metavar="NAME=RESULTS[#LABEL][,...]")
    parser.add_argument("--reference", default=None, help="default: the first name")
    parser.add_argument("--resamples", type=int, default=10000)
    parser.add_argument("--level", type=float, default=0.9)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if not 0 < args.level < 1:
        parser.error(f"--level {args.level}: between 0 and 1")
    if args.resamples < 1:
        parser.error(f"--resamples {args.resamples}: at least 1")
    scores = []
    for entry in args.entries:
        name, sep, spec = entry.partition("=")
        if not sep or not name or not spec:
            parser.error(f"{entry!r}: write NAME=RESULTS[#LABEL][,RESULTS[#LABEL]...]")
        if name in {s.name for s in scores}:
            parser.error(f"the name {name!r} is given twice")
        scores.append(read_scores(name, spec))
    reference = args.reference or scores[0].name
    rows = compare(scores, reference, args.resamples, args.level, args.seed)
    print(render(rows, reference, args.level))
    if args.json:
        Path(args.json).write_text(json.dumps(dict(reference=reference, level=args.level, rows=rows), indent=2))
    return rows


if __name__ == "__main__":
    try:
        main()
    except CompareError as err:
        raise SystemExit(f"error: {err}") from None
