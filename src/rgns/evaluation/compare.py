"""Is one simulator better than another on the same trajectories, or is it the draw of trajectories?

A split's rollout MSE is a mean over a few trajectories (8 on the default test split), and one
hard trajectory can carry half of it. This reads the per-trajectory rollout MSEs that
``evaluate.py`` wrote (``results.json``, forward task) for several methods, pairs each with a
reference method trajectory by trajectory, and reports the ratio of their means with a paired
bootstrap interval (the trajectories resampled with replacement, the same draw for both methods),
and on how many trajectories each is the lower::

    python -m rgns.evaluation.compare NAME=RUN[,RUN...] ... \\
        [--reference NAME] [--resamples 10000] [--level 0.9] [--seed 0] [--json out.json]

    RUN = RESULTS[#LABEL][+RESULTS[#LABEL]...]

``RESULTS`` is a ``results.json`` or the folder that holds it; ``LABEL`` the method's label in it,
needed only where the file holds several methods other than the training-free baselines. Several
runs for one name, joined by ``,``, are pooled (e.g. the test split's run and the selection split's:
their trajectories side by side); every name must then cover the same datasets and splits with the
same number of trajectories, in any order. Files joined by ``+`` are seeds of one method on one
split: each trajectory's error is their mean, the interval resamples the seeds too (with
replacement, independently per name) and the table gives the spread of the seeds' means. Where a
name pools splits, each split lists its seeds in the same order (the first file of each ``+`` group
is one model). The reference is the first name unless ``--reference`` says otherwise. An interval
that holds 1 says the trajectories (and seeds) cannot tell the two apart.
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
    """One method's per-trajectory rollout MSEs, by dataset and split, one row per seed."""

    name: str
    parts: dict[tuple[str, str], np.ndarray]  # (dataset, split) -> [seeds, trajectories]

    def pooled(self, keys: list[tuple[str, str]]) -> np.ndarray:
        """``[seeds, trajectories]``: the splits' trajectories side by side."""
        return np.concatenate([self.parts[key] for key in keys], axis=1)


def _results_path(path: str) -> Path:
    p = Path(path)
    p = p / "results.json" if p.is_dir() else p
    if not p.is_file():
        raise CompareError(f"{path}: no results.json there (evaluate.py writes one to its run folder)")
    return p


def _read_file(item: str) -> tuple[Path, dict[tuple[str, str], np.ndarray]]:
    """One ``RESULTS[#LABEL]``: its per-trajectory errors by (dataset, split)."""
    path, _, label = item.partition("#")
    file = _results_path(path)
    try:
        results = json.loads(file.read_text())
        datasets = results["datasets"]
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise CompareError(f"{file}: not an evaluate.py results.json ({err!r})") from None
    baselines = {k for k, v in results.get("methods", {}).items() if v.get("source") == "baseline"}
    parts = {}
    for dataset, section in datasets.items():
        methods = (section.get("forward") or {}).get("methods") or {}
        if not methods:
            raise CompareError(f"{file}: dataset {dataset} has no forward task's results")
        chosen = label or _only_trained(file, dataset, [m for m in methods if m not in baselines])
        if chosen not in methods:
            raise CompareError(f"{file}: no method {chosen!r} on {dataset}; it holds {sorted(methods)}")
        values = np.asarray(methods[chosen]["rollout_mse_per_trajectory"], dtype=float)
        if not np.all(np.isfinite(values)):
            raise CompareError(f"{file}: {chosen!r} on {dataset} has non-finite trajectory errors")
        parts[(dataset, str(section.get("split", "")))] = values
    return file, parts


def read_scores(name: str, spec: str) -> Scores:
    """The scores of ``NAME=RUN[,RUN...]``'s right-hand side, ``spec``."""
    parts: dict[tuple[str, str], np.ndarray] = {}
    for run in spec.split(","):
        seeds = [_read_file(item) for item in run.split("+")]
        first_file, first = seeds[0]
        for file, other in seeds[1:]:
            for key in sorted(set(first) | set(other)):
                if key not in first or key not in other:
                    raise CompareError(f"{name}: {file} and {first_file} are joined by + as seeds of one run "
                                       f"but do not both hold {key[0]} ({key[1]})")
                if len(other[key]) != len(first[key]):
                    raise CompareError(f"{name}: {file} has {len(other[key])} trajectories of {key[0]} ({key[1]}), "
                                       f"{first_file} {len(first[key])}")
        for key in first:
            if key in parts:
                raise CompareError(f"{name}: {key[0]} ({key[1]}) given twice")
            parts[key] = np.stack([values[key] for _, values in seeds])  # [S, T]
    counts = {key: v.shape[0] for key, v in parts.items()}
    if len(set(counts.values())) > 1:
        raise CompareError(f"{name}: its splits have different numbers of seeds ({counts}); "
                           "list each split's seeds in the same order")
    return Scores(name, parts)


def _only_trained(file: Path, dataset: str, labels: list[str]) -> str:
    if len(labels) != 1:
        raise CompareError(f"{file}: {dataset} holds {len(labels)} methods besides the baselines "
                           f"({labels}); name one as RESULTS#LABEL")
    return labels[0]


def _resample_counts(rng: np.random.Generator, n: int, resamples: int) -> np.ndarray:
    """``[resamples, n]``: how often each of ``n`` items is drawn in each resample of ``n`` with replacement."""
    index = rng.integers(0, n, size=(resamples, n))
    counts = np.zeros((resamples, n))
    np.add.at(counts, (np.arange(resamples)[:, None], index), 1.0)
    return counts


def paired_ratio(values: np.ndarray, reference: np.ndarray, resamples: int, level: float,
                 rng: np.random.Generator, seed_rngs: tuple[np.random.Generator, np.random.Generator] | None = None,
                 ) -> tuple[float, float, float]:
    """``mean(values) / mean(reference)`` and its paired bootstrap interval at ``level``. Shapes:
    ``[S, T]`` and ``[S_ref, T]`` (seeds, trajectories; a ``[T]`` vector is one seed). Each resample
    draws the trajectories with replacement, the same for both, and each one's seeds with replacement
    from ``seed_rngs`` (one generator per method; needed only where either has several seeds)."""
    values, reference = np.atleast_2d(values), np.atleast_2d(reference)
    ratio = float(values.mean() / reference.mean())
    trajectories = values.shape[1]
    counts = _resample_counts(rng, trajectories, resamples)  # [B, T]

    def draw(matrix: np.ndarray, seed_rng: np.random.Generator | None) -> np.ndarray:  # [B]
        seeds = matrix.shape[0]
        seed_counts = np.ones((resamples, 1)) if seeds == 1 else _resample_counts(seed_rng, seeds, resamples)
        return np.einsum("bs,st,bt->b", seed_counts, matrix, counts) / (seeds * trajectories)

    if seed_rngs is None and max(values.shape[0], reference.shape[0]) > 1:
        raise ValueError("paired_ratio: several seeds need seed_rngs")
    own, ref = seed_rngs or (None, None)
    draws = draw(values, own) / draw(reference, ref)
    tail = (1 - level) / 2
    low, high = np.quantile(draws, [tail, 1 - tail])
    return ratio, float(low), float(high)


def compare(scores: list[Scores], reference: str, resamples: int = 10000, level: float = 0.9,
            seed: int = 0) -> list[dict]:
    """One row per name: its pooled mean (over seeds and trajectories), its seeds' means and their
    spread, and against ``reference``'s the ratio of means, its paired bootstrap interval and the
    trajectories where each (its seeds' mean) is lower."""
    by_name = {s.name: s for s in scores}
    if reference not in by_name:
        raise CompareError(f"--reference {reference}: not one of the names {list(by_name)}")
    keys = sorted(by_name[reference].parts)
    for s in scores:
        if sorted(s.parts) != keys:
            raise CompareError(f"{s.name} covers {sorted(s.parts)}, {reference} {keys}: compare like with like")
        for key in keys:
            mine, theirs = s.parts[key].shape[1], by_name[reference].parts[key].shape[1]
            if mine != theirs:
                raise CompareError(f"{s.name} has {mine} trajectories of {key[0]} ({key[1]}), {reference} {theirs}")
    base = by_name[reference].pooled(keys)  # [S_ref, T]
    rows = []
    for position, s in enumerate(scores):
        values = s.pooled(keys)  # [S, T]
        per_seed = values.mean(1)
        row = dict(name=s.name, seeds=int(values.shape[0]), trajectories=int(values.shape[1]),
                   mean=float(values.mean()), seed_means=per_seed.tolist(),
                   seed_std=float(per_seed.std(ddof=1)) if len(per_seed) > 1 else 0.0)
        if s.name != reference:
            rng = np.random.default_rng(seed)  # the same draws of trajectories for every name
            # each name's seeds drawn from its own stream, the reference's from one stream for all
            seed_rngs = (np.random.default_rng([seed, 1, position]), np.random.default_rng([seed, 2]))
            ratio, low, high = paired_ratio(values, base, resamples, level, rng, seed_rngs)
            mine, theirs = values.mean(0), base.mean(0)
            row.update(ratio=ratio, low=low, high=high, lower=int((mine < theirs).sum()),
                       higher=int((mine > theirs).sum()))
        rows.append(row)
    return rows


def render(rows: list[dict], reference: str, level: float) -> str:
    lines = [f"| name | seeds | trajectories | rollout MSE (1e-3) | sd over seeds | ratio to {reference} "
             f"| {level:.0%} interval | lower / higher |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        spread = f"{r['seed_std'] * 1e3:.4g}" if r["seeds"] > 1 else ""
        head = f"| {r['seeds']} | {r['trajectories']} | {r['mean'] * 1e3:.4g} | {spread} "
        if "ratio" in r:
            lines.append(f"| {r['name']} {head}| {r['ratio']:.3f} | {r['low']:.3f}-{r['high']:.3f} "
                         f"| {r['lower']} / {r['higher']} |")
        else:
            lines.append(f"| {r['name']} (reference) {head}| 1 | | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(prog="python -m rgns.evaluation.compare", description=__doc__.split("\n\n")[0])
    parser.add_argument("entries", nargs="+", metavar="NAME=RESULTS[#LABEL][+...][,...]")
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
            parser.error(f"{entry!r}: write NAME=RESULTS[#LABEL][+RESULTS[#LABEL]...][,...]")
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
