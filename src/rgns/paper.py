"""The paper's tables across benchmarks, from checkpoints, by one command:
``python -m rgns.paper [key=value ...]`` (``bash scripts/paper.sh``; docs/paper.md).

The manifest ``conf/paper.yaml`` lists the benchmarks, each with its test dataset and, per set of
checkpoints (the main budget's seeds, the shipped long-trained files) and method, the globs of its
checkpoint files (one file a run). Every checkpoint is evaluated by the project's own evaluation
(:func:`rgns.evaluation.run.evaluate`: ``task=forward``, ``inverse``, ``efficiency`` and the
feed-forward rows of ``inverse_optimisation``, no baselines), the yardsticks (constant velocity,
ballistic with walls, the dataset's solver at a coarser grid and its predictability floor) and the
optimisation baselines of Table 3 (:func:`rgns.inverse.tasks.compare_inverse`) once per benchmark.
Each result is cached under ``cache_dir``, keyed by the checkpoint's content hash, the dataset's
and the evaluation settings, so a rerun evaluates only what is new.

Out, in ``out_dir``:

- ``tables.md``: Table 1 (test rollout MSE, rows: benchmark and set, columns: NeuralSPH, EGNN,
  DMCF, GNS, R-GNS†, R-GNS, each "mean ± std (n)" over the set's runs, beside the yardsticks),
  Table 2 (parameters, ms per forward step, peak memory), Table 3 (inverse at K = 40: consistency,
  inverse MSE, time, max stable steps of R-GNS, Sep-GNS and the solvers + Adam), the ablation
  table, and every method without checkpoints with the reason;
- ``paper.json``: every number and where it came from (checkpoint, seed, cache folder);
- ``rollout_mse.png``, ``accuracy_vs_speed.png`` and ``ablation.png`` (where ablation runs exist).

It runs both the evaluation and the inverse optimisers, so it sits above every layer of the
package (README, Layout), as ``train.py`` and ``evaluate.py`` do.
"""
from __future__ import annotations

import glob
import hashlib
import json
import logging
import math
import os
import shutil
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from rgns import config_dir
from rgns.evaluation.methods import build_baselines
from rgns.evaluation.plots import save_figure, write_whole
from rgns.evaluation.report import GAP, number, steps_cell, table
from rgns.evaluation.run import evaluate, summarise
from rgns.evaluation.tasks import Dataset
from rgns.inverse.tasks import chosen_optimisers, compare_inverse
from rgns.training.stages import sha256

import matplotlib.pyplot as plt  # noqa: E402 - after rgns.evaluation.plots has chosen the Agg backend
from matplotlib.ticker import NullFormatter  # noqa: E402

log = logging.getLogger(__name__)

KEY_VERSION = 1  # part of every cache key: bump when what a cached result holds changes
NOT_TRAINED = "not trained"
BASELINES = {"constant_velocity": "Const. velocity", "ballistic": "Ballistic + walls"}
YARDSTICKS = ("coarse_solver", "floor", "constant_velocity", "ballistic")
YARDSTICK_NAMES = {"coarse_solver": "Solver, coarser grid", "floor": "Predictability floor",
                   "constant_velocity": "Const. velocity", "ballistic": "Ballistic + walls"}


# ------------------------------------------------------------------------------------ the manifest

def compose_config(name: str, overrides: list[str]) -> DictConfig:
    """``conf/<name>.yaml`` composed with ``overrides`` (Hydra's syntax)."""
    with initialize_config_dir(str(config_dir()), version_base="1.3"):
        return compose(name, overrides=list(overrides))


def override_value(value) -> str:
    """A value in Hydra's override syntax: ``null``, ``true``, ``[1,5]``, ``{a:1}``, ``'text'``."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(override_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{override_value(v)}" for k, v in value.items()) + "}"
    return "'" + str(value).replace("\\", "\\\\").replace("'", "\\'") + "'"


def flatten(node: dict, prefix: str = "") -> list[str]:
    """``{task: {forward: {steps: 300}}}`` -> ``["task.forward.steps=300"]``; lists are leaves."""
    out = []
    for key, value in node.items():
        if isinstance(value, dict) and value:
            out += flatten(value, f"{prefix}{key}.")
        else:
            out.append(f"{prefix}{key}={override_value(value)}")
    return out


def evaluation_config(manifest: DictConfig, checkpoint: str | None, root: str, out: str) -> DictConfig:
    """``evaluate.py``'s config for one checkpoint on ``root`` (or, ``checkpoint=None``, the
    settings the yardsticks and optimisers share): the manifest's ``evaluate`` settings with the
    four tasks, no baselines, references or no-hard-walls twins beside the checkpoint, and the
    feed-forward rows only of ``inverse_optimisation`` (its optimisers run once per benchmark)."""
    settings = OmegaConf.to_container(manifest.evaluate, resolve=True)
    overrides = ["task=[all,inverse_optimisation]", *flatten(settings), f"data_root={override_value(root)}",
                 f"output_dir={override_value(out)}"]
    if checkpoint is not None:
        overrides += [f"ckpt_path={override_value(checkpoint)}", "without_hard_walls=false"]
    cfg = compose_config("evaluate", overrides)
    if checkpoint is not None:  # the yardsticks are measured once per benchmark, not beside each checkpoint
        cfg.baselines, cfg.references = None, None
    mine = cfg.task.inverse_optimisation
    mine.optimisers, mine.stability_steps, mine.budget_iterations = {}, 0, 0
    return cfg


def key_material(cfg: DictConfig) -> dict:
    """The resolved config, with this machine's paths taken out (their contents are hashed instead)."""
    plain = OmegaConf.to_container(cfg, resolve=True)
    for name in ("output_dir", "ckpt_path", "data_root"):
        plain.pop(name, None)
    plain["task"]["inverse_optimisation"].pop("out_dir", None)
    return plain


# -------------------------------------------------------------------------------------- the cache

def data_hash(root: str | Path, split: str) -> str:
    """The content of a dataset as an evaluation reads it: its metadata and the split."""
    return hashlib.sha256((sha256(Path(root) / "metadata.json") + sha256(Path(root) / f"{split}.h5"))
                          .encode()).hexdigest()


class Cache:
    """One folder per key under ``folder``: the evaluation's files, with ``key.json`` (what the
    key was made of). A folder is complete or absent: each is written beside, then renamed."""

    def __init__(self, folder: str | Path, refresh: bool = False):
        self.folder, self.refresh = Path(folder), refresh

    @staticmethod
    def key(material: dict) -> str:
        text = json.dumps(dict(material, key_version=KEY_VERSION), sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:20]

    def load(self, key: str, name: str) -> dict | None:
        path = self.folder / key / name
        if self.refresh or not path.is_file():
            return None
        try:
            return json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as error:
            log.warning("%s: unreadable (%s); evaluating again", path, error)
            return None

    def obtain(self, material: dict, name: str, make, recorded: dict | None = None) -> tuple[dict, dict]:
        """The JSON file ``name`` of the entry keyed by ``material``: from the cache when there, else
        written by ``make(folder)`` (:meth:`fill`; ``recorded``, default ``material``, as its
        ``key.json``); and where it came from (``cache``: its folder, ``cached``, ``seconds``)."""
        key = self.key(material)
        found = self.load(key, name)
        if found is not None:
            return found, dict(cache=str(self.folder / key), cached=True, seconds=None)
        begin = time.perf_counter()
        folder = self.fill(key, material if recorded is None else recorded, make)
        return json.loads((folder / name).read_text()), dict(
            cache=str(folder), cached=False, seconds=time.perf_counter() - begin)

    def fill(self, key: str, material: dict, make) -> Path:
        """``make(folder)`` writes into a fresh temporary folder, which becomes ``<key>/``."""
        self.folder.mkdir(parents=True, exist_ok=True)
        temporary = self.folder / f".{key}.{os.getpid()}.tmp"
        shutil.rmtree(temporary, ignore_errors=True)
        temporary.mkdir()
        try:
            make(temporary)
            write_whole(temporary / "key.json", (json.dumps(material, indent=2, default=str) + "\n").encode())
            final = self.folder / key
            if final.exists():  # refresh=true, or another run finished first: the newer result wins
                shutil.rmtree(final)
            os.rename(temporary, final)
            return final
        finally:
            shutil.rmtree(temporary, ignore_errors=True)


# ------------------------------------------------------------------------------------- evaluations

def checkpoint_results(path: Path, root: str, manifest: DictConfig, cache: Cache) -> tuple[dict, dict]:
    """``results.json`` of one checkpoint's evaluation on ``root``, from the cache when there;
    and where it came from (``cache``: its folder, ``cached``, ``seconds``)."""
    cfg = evaluation_config(manifest, str(path), root, "<out>")
    material = dict(kind="checkpoint", checkpoint=sha256(path), data=data_hash(root, cfg.split),
                    evaluate=key_material(cfg))

    def make(folder: Path) -> None:
        log.info("evaluating %s on %s", path, root)
        cfg.output_dir = str(folder)
        evaluate(cfg)

    return cache.obtain(material, "results.json", make, dict(material, first_path=str(path)))


def yardstick_results(root: str, manifest: DictConfig, cache: Cache) -> tuple[dict, dict]:
    """The training-free baselines and the solver references on ``root``'s test trajectories:
    the evaluation's forward task on them, its summary, and each reference's ms per frame."""
    cfg = evaluation_config(manifest, None, root, "<out>")
    history = int(manifest.history)
    plain = key_material(cfg)
    material = dict(kind="yardsticks", data=data_hash(root, cfg.split), history=history,
                    **{k: plain.get(k) for k in ("split", "trajectories", "start", "device", "threads", "precision",
                                                 "baselines", "references", "divergence")},
                    forward=plain["task"]["forward"])

    def make(folder: Path) -> None:
        import torch

        log.info("yardsticks on %s", root)
        torch.set_num_threads(cfg.threads)
        dataset = Dataset.load(root, cfg.split, cfg.trajectories, history, cfg.start, cfg.device)
        baselines = build_baselines(cfg.baselines, dataset.metadata, history, cfg.device)
        make_references = instantiate(cfg.references, _convert_="all") if cfg.get("references") else None
        references, note = make_references(dataset) if make_references else ([], None)
        forward = instantiate(cfg.task.forward, _convert_="all")
        sections = dict(root=str(Path(root).resolve()), split=cfg.split)
        sections["forward"], _ = forward(baselines + references, dataset)
        sections["efficiency"] = dict(methods={r.label: r.cost(dataset) for r in references})
        if make_references:
            sections["references"] = dict(settings=make_references.settings(), note=note,
                                          methods={r.label: r.describe() for r in references})
        sections = json.loads(json.dumps(sections))
        sections["summary"] = summarise(sections)
        write_whole(folder / "yardsticks.json", (json.dumps(sections, indent=2) + "\n").encode())

    return cache.obtain(material, "yardsticks.json", make)


def optimiser_results(root: str, manifest: DictConfig, cache: Cache) -> tuple[dict | None, dict]:
    """The optimisation baselines (``manifest.optimisers``) on the trajectories and horizons of
    the checkpoints' ``inverse_optimisation`` task: :func:`~rgns.inverse.tasks.compare_inverse`
    with no learned model. ``None`` where no optimiser is asked for."""
    optimisers = chosen_optimisers(OmegaConf.to_container(manifest.optimisers, resolve=True))
    if not optimisers:
        return None, dict(reason="no optimiser in the manifest (optimisers)")
    cfg = evaluation_config(manifest, None, root, "<out>")
    task = OmegaConf.to_container(cfg.task.inverse_optimisation, resolve=True)
    material = dict(kind="optimisers", data=data_hash(root, cfg.split), split=cfg.split, start=cfg.start,
                    history=int(manifest.history), optimisers=optimisers,
                    **{k: task.get(k) for k in ("horizons", "trajectories", "rule", "threshold", "table_horizon")})

    def make(folder: Path) -> None:
        import torch

        log.info("optimisers %s on %s", ", ".join(optimisers), root)
        torch.set_num_threads(cfg.threads)
        dataset = Dataset.load(root, cfg.split, task["trajectories"], int(manifest.history), cfg.start, cfg.device)
        compare_inverse({}, dataset.metadata, dataset.trajectories, task["horizons"], start=dataset.start,
                        optimisers=optimisers, rule=task.get("rule"), threshold=task["threshold"],
                        table_horizon=task["table_horizon"], out_dir=folder)

    return cache.obtain(material, "inverse_comparison.json", make)


# -------------------------------------------------------------------------------- runs and numbers

def find_runs(patterns) -> list[dict]:
    """The runs a method's globs name: ``{"checkpoint": path}`` per folder (its newest match), or
    ``{"results": path, "label": label}`` for an entry ``<results.json>#<label>``."""
    runs, folders = [], {}
    for pattern in patterns or []:
        pattern = str(pattern)
        if "#" in pattern:
            path, label = pattern.split("#", 1)
            runs += [dict(results=str(Path(p)), label=label) for p in sorted(glob.glob(path))]
            continue
        for match in sorted(glob.glob(pattern)):
            path = Path(match).resolve()
            if path.is_file():
                folders.setdefault(path.parent, set()).add(path)
    for folder, paths in sorted(folders.items()):
        runs.append(dict(checkpoint=str(max(paths, key=lambda p: (p.stat().st_mtime, p.name)))))
    return runs


def record(results: dict, label: str | None, source: str) -> dict:
    """The numbers the tables need of one method in an evaluation's ``results.json``: the trained
    method there (or ``label``), its summary, and its feed-forward row of ``inverse_optimisation``."""
    if len(results.get("datasets", {})) != 1:
        raise ValueError(f"{source}: holds {len(results.get('datasets', {}))} datasets; the paper reads one per file")
    (name, data), = results["datasets"].items()
    trained = [m for m, info in results["methods"].items() if info.get("source") not in ("baseline", "reference")
               and info.get("hard_walls") is not False]
    if label is None:
        if len(trained) != 1:
            raise ValueError(f"{source}: {len(trained)} trained methods ({', '.join(trained)}); name one with #<label>")
        label = trained[0]
    if label not in data.get("summary", {}):
        raise ValueError(f"{source}: no method {label!r} on {name} (there: {', '.join(data.get('summary', {}))})")
    info, row = results["methods"].get(label, {}), data["summary"][label]
    out = dict(label=label, source=info.get("source", source), seed=info.get("seed"), global_step=info.get("global_step"),
               dataset=name, **{k: row[k] for k in (  # absent: not measured (a forward-only model's inverse)
                   "rollout_mse", "stable_steps", "diverged", "parameters", "forward_ms_per_step", "memory_mb",
                   "consistency_mse", "inverse_mse", "max_stable_steps", "stable_beyond_tested") if k in row})
    forward = data.get("forward", {}).get("settings", {})
    out.update(trajectories=forward.get("trajectories"), steps=forward.get("steps"), start=forward.get("start"))
    comparison = data.get("inverse_optimisation")
    if comparison and label in comparison.get("methods", {}):
        K = str(comparison["settings"]["table_horizon"])
        method = comparison["methods"][label]
        at = method["horizons"].get(K) or {}
        out["inverse_optimisation"] = dict(horizon=int(K), consistency_mse=at.get("consistency_mse"),
                                           inverse_mse=at.get("inverse_mse"), seconds=at.get("seconds"),
                                           max_stable_steps=method["max_stable_steps"],
                                           stable_beyond_tested=method["stable_beyond_tested"],
                                           trajectories=comparison["settings"]["trajectories"])
    return out


def statistics(values) -> dict | None:
    """Mean and sample standard deviation (n - 1) of the finite values; ``None`` for no values.
    ``n``: the values; ``not_finite``: how many of them were not finite (a diverged run)."""
    values = list(values)
    if not values:
        return None
    finite = [float(v) for v in values if v is not None and math.isfinite(v)]
    return dict(n=len(values), not_finite=len(values) - len(finite), values=values,
                mean=float(np.mean(finite)) if finite else None,
                std=float(np.std(finite, ddof=1)) if len(finite) > 1 else None,
                min=min(finite) if finite else None, max=max(finite) if finite else None)


def cell(stats: dict | None, scale: float = 1.0, count: bool = True) -> str:
    """``4.51 ± 0.36 (3)``; ``7.36 (1)`` for one run; a note for values that were not finite."""
    if stats is None:
        return GAP
    if stats["mean"] is None:
        return f"not finite ({stats['n']})"
    text = number(stats["mean"], scale) + ("" if stats["std"] is None else f" ± {number(stats['std'], scale, 2)}")
    if count:
        text += f" ({stats['n']}" + (f", {stats['not_finite']} not finite" if stats["not_finite"] else "") + ")"
    return text


def parameters_cell(stats: dict | None) -> str:
    """The parameter count of a set's runs: one number, or the least and greatest where they differ."""
    if stats is None or stats["mean"] is None:
        return GAP
    low, high = int(stats["min"]), int(stats["max"])
    return f"{low:,}" if low == high else f"{low:,}–{high:,}"


def method_entry(patterns, results_of) -> dict:
    """One method of one set: its runs (each a :func:`record`, or the reason it could not be read)
    and the statistics over them."""
    runs = find_runs(patterns)
    if not runs:
        globs = ", ".join(f"`{p}`" for p in patterns or [])
        return dict(status=NOT_TRAINED, runs=[], reason=f"no checkpoint matches {globs}" if globs
                    else "no checkpoint listed in the manifest")
    records, failures = [], []
    for run in runs:
        try:
            records.append(results_of(run))
        except Exception as error:  # noqa: BLE001 - one unreadable run is named, the others are reported
            where = run.get("checkpoint") or run.get("results")
            log.warning("%s: not evaluated (%s: %s)", where, type(error).__name__, error)
            failures.append(f"{type(error).__name__}: {error}" if where in str(error)
                            else f"{where}: {type(error).__name__}: {error}")
    entry = dict(status="evaluated" if records else "not evaluated", runs=records, failed=failures)
    if not records:
        entry["reason"] = "; ".join(failures)
        return entry
    seeds = [r.get("seed") for r in records]
    entry.update(labels=sorted({r["label"] for r in records}), seeds=seeds,
                 repeated_seeds=len([s for s in seeds if s is not None]) != len({s for s in seeds if s is not None}))
    for key in ("rollout_mse", "parameters", "forward_ms_per_step", "memory_mb", "consistency_mse", "inverse_mse"):
        measured = [r[key] for r in records if key in r]
        entry[key] = statistics(measured) if measured else None
    feed_forward = [r["inverse_optimisation"] for r in records if "inverse_optimisation" in r]
    if feed_forward:
        entry["inverse_optimisation"] = dict(
            horizon=feed_forward[0]["horizon"], trajectories=feed_forward[0]["trajectories"],
            **{k: statistics([f[k] for f in feed_forward]) for k in ("consistency_mse", "inverse_mse", "seconds")},
            max_stable_steps=[steps_cell(f["max_stable_steps"], f["stable_beyond_tested"]) for f in feed_forward])
    return entry


# ------------------------------------------------------------------------------------- the whole

def yardstick_numbers(sections: dict) -> dict:
    """Rollout MSE (and ms per frame) of the four yardsticks, with the label each came from."""
    summary = sections["summary"]
    references = sections.get("references", {}).get("methods", {})
    coarse = [label for label, info in references.items() if info.get("perturbation") is None]
    floor = [label for label, info in references.items() if info.get("perturbation") is not None]
    coarse.sort(key=lambda label: references[label].get("n_grid") or 0)
    chosen = dict(coarse_solver=coarse[0] if coarse else None, floor=floor[0] if floor else None,
                  constant_velocity=BASELINES["constant_velocity"], ballistic=BASELINES["ballistic"])
    out = {}
    for name, label in chosen.items():
        row = summary.get(label) if label else None
        out[name] = None if row is None else dict(label=label, rollout_mse=row.get("rollout_mse"),
                                                  forward_ms_per_step=row.get("forward_ms_per_step"))
    out["note"] = sections.get("references", {}).get("note")
    return out


def missing_dataset(spec: DictConfig) -> str | None:
    """Why a benchmark of the manifest cannot be evaluated for want of its test dataset (and how to
    make it), or ``None`` where ``spec.data`` holds one."""
    missing = [f for f in ("metadata.json", "test.h5") if not (Path(spec.data) / f).is_file()]
    if not missing:
        return None
    return (f"no dataset: {spec.data} lacks {', '.join(missing)}"
            + (f" (make it: `{spec.make}`)" if spec.get("make") else ""))


def benchmark(name: str, spec: DictConfig, manifest: DictConfig, cache: Cache) -> dict:
    """Every set, method, yardstick, optimiser and ablation variant of one benchmark."""
    root = str(spec.data)
    out = dict(data=root, sets={}, ablation={})
    missing = missing_dataset(spec)
    if missing:
        out.update(status=NOT_TRAINED, reason=missing)
        return out
    out["status"] = "evaluated"
    provenance: list[dict] = []

    def results_of(run: dict) -> dict:
        if "results" in run:
            return dict(record(json.loads(Path(run["results"]).read_text()), run["label"], run["results"]),
                        results_file=run["results"])
        results, where = checkpoint_results(Path(run["checkpoint"]), root, manifest, cache)
        provenance.append(dict(checkpoint=run["checkpoint"], **where))
        return dict(record(results, None, run["checkpoint"]), checkpoint=run["checkpoint"], cache=where["cache"])

    columns = {**manifest.methods, **manifest.inverse_methods}
    for set_name, group in (spec.get("sets") or {}).items():
        methods = group.get("methods") or {}
        out["sets"][set_name] = dict(label=group.get("label", set_name), about=group.get("about"), methods={
            key: method_entry(methods.get(key), results_of) for key in columns})
    for variant in manifest.ablation_variants:
        patterns = (spec.get("ablation") or {}).get(variant)
        out["ablation"][variant] = method_entry(patterns, results_of)
    try:
        sections, where = yardstick_results(root, manifest, cache)
        out["yardsticks"] = dict(yardstick_numbers(sections), **where)
    except Exception as error:  # noqa: BLE001 - reported in the tables, not a crash
        log.warning("%s: yardsticks not measured (%s: %s)", name, type(error).__name__, error)
        out["yardsticks"] = dict(error=f"{type(error).__name__}: {error}")
    try:
        comparison, where = optimiser_results(root, manifest, cache)
        out["optimisers"] = dict(where, **({} if comparison is None else optimiser_rows(comparison)))
    except Exception as error:  # noqa: BLE001
        log.warning("%s: optimisers not run (%s: %s)", name, type(error).__name__, error)
        out["optimisers"] = dict(error=f"{type(error).__name__}: {error}")
    out["evaluations"] = provenance
    return out


def optimiser_rows(comparison: dict) -> dict:
    """Each optimiser's row of Table 3 from a :func:`compare_inverse` result."""
    K = str(comparison["settings"]["table_horizon"])
    rows = {}
    for label, method in comparison["methods"].items():
        at = method["horizons"].get(K)
        rows[label] = dict(horizons_run=sorted(int(k) for k in method["horizons"]),
                           consistency_mse=None if at is None else at["consistency_mse"],
                           inverse_mse=None if at is None else at["inverse_mse"],
                           seconds=None if at is None else at["seconds"],
                           statuses=None if at is None else at["statuses"],
                           max_stable_steps=steps_cell(method["max_stable_steps"], method["stable_beyond_tested"]))
    return dict(horizon=int(K), trajectories=comparison["settings"]["trajectories"], methods=rows)


def build(manifest: DictConfig, argv: list[str]) -> dict:
    cache = Cache(manifest.cache_dir, bool(manifest.refresh))
    settings = OmegaConf.to_container(manifest.evaluate, resolve=True)
    paper = dict(command=" ".join(["python -m rgns.paper", *argv]),
                 date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                 manifest=OmegaConf.to_container(manifest, resolve=True), evaluate=settings, benchmarks={})
    for name, spec in manifest.benchmarks.items():
        paper["benchmarks"][name] = benchmark(name, spec, manifest, cache)
    return paper


# ----------------------------------------------------------------------------------------- tables

def reasons(entries: dict, names: dict) -> list[str]:
    return [f"{names.get(key, key)}: {entry['status']} ({entry['reason']})" for key, entry in entries.items()
            if entry.get("reason")]


def seeds_text(seeds: list) -> str:
    """``seeds 0, 1, 2``; ``seed not recorded`` for files without their run's config (shipped files)."""
    if all(seed is None for seed in seeds):
        return "seed not recorded" if len(seeds) == 1 else f"{len(seeds)} files, seeds not recorded"
    return "seeds " + ", ".join("?" if seed is None else str(seed) for seed in seeds)


def table_one(paper: dict, manifest: DictConfig) -> list[str]:
    methods = dict(manifest.methods)
    header = ["Benchmark (set)", *methods.values(), *(YARDSTICK_NAMES[y] for y in YARDSTICKS)]
    rows, notes = [], []
    for name, bench in paper["benchmarks"].items():
        if bench["status"] != "evaluated":
            rows.append([name, *([NOT_TRAINED] * len(methods)), *([GAP] * len(YARDSTICKS))])
            notes.append(f"- {name}: {bench['reason']}")
            continue
        yard = bench.get("yardsticks", {})
        yard_cells = [GAP if not yard.get(y) else number(yard[y]["rollout_mse"], 1e3) for y in YARDSTICKS]
        for set_name, group in bench["sets"].items():
            entries = {k: group["methods"][k] for k in methods}
            rows.append([f"{name} ({group['label']})",
                         *(cell(e.get("rollout_mse"), 1e3) if e["status"] == "evaluated" else e["status"]
                           for e in entries.values()), *yard_cells])
            missing = reasons(entries, methods)
            if missing:
                notes.append(f"- {name} ({group['label']}): " + "; ".join(missing))
            models = [f"{methods[k]}: {', '.join(e['labels'])} ({seeds_text(e['seeds'])}"
                      + (": a seed repeated, so fewer independent runs than n" if e["repeated_seeds"] else "") + ")"
                      for k, e in entries.items() if e["status"] == "evaluated"]
            if models:
                notes.append(f"- {name} ({group['label']}) models: " + "; ".join(models))
        labels = [f"{YARDSTICK_NAMES[y]}: {yard[y]['label']}" for y in ("coarse_solver", "floor") if yard.get(y)]
        if labels or yard.get("note") or yard.get("error"):
            notes.append(f"- {name} yardsticks: " + "; ".join(labels + [yard.get("note") or "", yard.get("error") or ""]).strip("; "))
    settings = paper["evaluate"]
    return ["## Table 1: test rollout MSE (1e-3)", "",
            f"Mean ± sample std over the set's runs (n: runs; one run has no spread). Each run scored on the first "
            f"{settings.get('trajectories')} test trajectories, {settings['task']['forward']['steps']}-step rollouts "
            f"from frame {settings.get('start')}, as trained (hard walls where the model has them). "
            "Yardsticks on the same trajectories and frames.", "", table(header, rows), "", *notes]


def table_two(paper: dict, manifest: DictConfig) -> list[str]:
    columns = {**manifest.methods, **manifest.inverse_methods}
    out = ["## Table 2: cost per benchmark", "",
           "Parameters, forward ms per step (radius graph included, median of warm repeats on one thread) and "
           "peak memory of a step (MB): mean ± std over the set's runs (n). The solver at a coarser grid: ms per "
           "frame of its own rollout."]
    for name, bench in paper["benchmarks"].items():
        if bench["status"] != "evaluated":
            out += ["", f"### {name}", "", f"{NOT_TRAINED}: {bench['reason']}"]
            continue
        rows = []
        for group in bench["sets"].values():
            for key, entry in group["methods"].items():
                if entry["status"] != "evaluated":
                    continue
                rows.append([f"{columns[key]} ({group['label']})", ", ".join(entry["labels"]),
                             parameters_cell(entry["parameters"]), cell(entry["forward_ms_per_step"]),
                             cell(entry["memory_mb"])])
        coarse = bench.get("yardsticks", {}).get("coarse_solver")
        if coarse:
            rows.append([YARDSTICK_NAMES["coarse_solver"], coarse["label"], "0", number(coarse["forward_ms_per_step"]), GAP])
        out += ["", f"### {name}", "", table(["Method (set)", "Model", "Parameters", "Forward ms/step",
                                              "Peak memory (MB)"], rows) if rows else "No model evaluated."]
    return out


def table_three(paper: dict, manifest: DictConfig) -> list[str]:
    inverse = dict(manifest.inverse_methods)
    settings = paper["evaluate"]["task"]["inverse_optimisation"]
    K = settings["table_horizon"]
    out = [f"## Table 3: inverse at K = {K}", "",
           f"The evaluation's inverse_optimisation task on the first {settings['trajectories']} test "
           f"trajector{'y' if settings['trajectories'] == 1 else 'ies'}: from the true state at t0 + K, K inverse "
           "steps of a model (feed-forward) or Adam on the initial state through a differentiable solver, then K "
           "forward steps of the method's own simulator; consistency MSE against the truth at t0 + K, inverse MSE "
           f"against t0 (moving particles), wall time, and max stable steps (horizons {settings['horizons']}, "
           "consistency under 1e-3 and no failure; ≥: every K tried). MSE in 1e-3; models: mean ± std (n) over the "
           "set's runs, stable steps per run."]
    for name, bench in paper["benchmarks"].items():
        if bench["status"] != "evaluated":
            out += ["", f"### {name}", "", f"{NOT_TRAINED}: {bench['reason']}"]
            continue
        rows, notes = [], []
        for group in bench["sets"].values():
            for key, label in inverse.items():
                entry = group["methods"][key]
                ff = entry.get("inverse_optimisation")
                if entry["status"] != "evaluated" or not ff:
                    notes.append(f"{label} ({group['label']}): {entry['status']}"
                                 + (f" ({entry['reason']})" if entry.get("reason") else ""))
                    continue
                rows.append([f"{label} ({group['label']})", cell(ff["consistency_mse"], 1e3), cell(ff["inverse_mse"], 1e3),
                             cell(ff["seconds"]), " / ".join(ff["max_stable_steps"])])
        optimisers = bench.get("optimisers", {})
        for label, row in optimisers.get("methods", {}).items():
            status = ", ".join(row["statuses"]) if row["statuses"] else f"not run at K = {K} (run: K = {row['horizons_run']})"
            rows.append([f"{label} ({status})", number(row["consistency_mse"], 1e3), number(row["inverse_mse"], 1e3),
                         number(row["seconds"]), row["max_stable_steps"]])
        if optimisers.get("error") or optimisers.get("reason"):
            notes.append(f"solver + Adam: not run ({optimisers.get('error') or optimisers.get('reason')})")
        out += ["", f"### {name}", "",
                table(["Method", "Consistency MSE (1e-3)", "Inverse MSE (1e-3)", "Time (s)", "Max stable steps"], rows)
                if rows else "Nothing evaluated.", *([""] + [f"- {n}" for n in notes] if notes else [])]
    return out


def ablation_table(paper: dict, manifest: DictConfig) -> list[str]:
    variants = dict(manifest.ablation_variants)
    K = paper["evaluate"]["task"]["inverse"]["table_horizon"]
    out = ["## Ablations", "",
           f"Each variant's runs (n): test rollout MSE and consistency MSE at K = {K} (the evaluation's inverse task, "
           "every test trajectory scored), 1e-3, mean ± std. Figure: ablation.png."]
    for name, bench in paper["benchmarks"].items():
        entries = bench.get("ablation", {})
        if bench["status"] != "evaluated" or not any(e["status"] == "evaluated" for e in entries.values()):
            out += ["", f"### {name}", "", f"No ablation runs: {bench.get('reason') or 'no checkpoint for any variant'}."]
            continue
        rows = [[variants[v], cell(e.get("rollout_mse"), 1e3), cell(e.get("consistency_mse"), 1e3)]
                if e["status"] == "evaluated" else [variants[v], e["status"], e["status"]] for v, e in entries.items()]
        out += ["", f"### {name}", "", table(["Variant", "Rollout MSE (1e-3)", f"Consistency MSE (1e-3), K = {K}"], rows)]
    return out


def render(paper: dict, manifest: DictConfig, charts: list[str]) -> str:
    sets = {}
    for bench in paper["benchmarks"].values():
        for group in bench.get("sets", {}).values():
            sets.setdefault(group["label"], group.get("about"))
    lines = ["# The paper's tables across benchmarks", "", f"Reproduce with: `{paper['command']}` (run {paper['date']}).",
             "", "Sets of runs:", "", *(f"- {label}: {about}" for label, about in sets.items()), "",
             *table_one(paper, manifest), "", *table_two(paper, manifest), "", *table_three(paper, manifest), "",
             *ablation_table(paper, manifest), "", "## Charts", "", *(f"![{c}]({c})" for c in charts)]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------- charts

def _finite_mean(stats):
    return None if stats is None else stats.get("mean")


def _std(stats):
    return 0.0 if stats is None or stats.get("std") is None else stats["std"]


def rollout_chart(paper: dict, manifest: DictConfig, path: Path) -> bool:
    """Table 1 as bars (log scale) with std error bars, the yardsticks as lines, a panel per benchmark."""
    methods = dict(manifest.methods)
    panels = [(n, b) for n, b in paper["benchmarks"].items() if b["status"] == "evaluated"]
    if not panels:
        return False
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.2), squeeze=False)
    for ax, (name, bench) in zip(axes[0], panels):
        sets = list(bench["sets"].items())
        width = 0.8 / max(len(sets), 1)
        for s, (set_name, group) in enumerate(sets):
            xs, ys, errors = [], [], []
            for m, key in enumerate(methods):
                stats = group["methods"][key].get("rollout_mse")
                if _finite_mean(stats) is not None:
                    xs.append(m + (s - (len(sets) - 1) / 2) * width)
                    ys.append(1e3 * stats["mean"])
                    errors.append(1e3 * _std(stats))
            if xs:
                ax.bar(xs, ys, width, yerr=errors, capsize=3, label=group["label"])
        for y, style, colour in zip(YARDSTICKS, ("--", "-.", ":", ":"), ("black", "grey", "tab:red", "tab:purple")):
            row = bench.get("yardsticks", {}).get(y)
            if row and row.get("rollout_mse"):
                ax.axhline(1e3 * row["rollout_mse"], color=colour, linestyle=style, linewidth=1, label=row["label"])
        ax.set_xticks(range(len(methods)), list(methods.values()), rotation=30)
        ax.set_yscale("log")
        ax.set_ylabel("test rollout MSE (1e-3)")
        ax.set_title(name)
        ax.legend(fontsize=7)
    save_figure(fig, path)
    return True


def speed_chart(paper: dict, manifest: DictConfig, path: Path) -> bool:
    """Rollout MSE against forward ms per step, each method and set a point with std error bars."""
    columns = {**manifest.methods, **manifest.inverse_methods}
    panels = [(n, b) for n, b in paper["benchmarks"].items() if b["status"] == "evaluated"]
    points = [(n, b) for n, b in panels if any(_finite_mean(e.get("rollout_mse")) is not None
                                               for g in b["sets"].values() for e in g["methods"].values())]
    if not points:
        return False
    fig, axes = plt.subplots(1, len(points), figsize=(8.5 * len(points), 4.5), squeeze=False)
    for ax, (name, bench) in zip(axes[0], points):
        for group in bench["sets"].values():
            for key, entry in group["methods"].items():
                mse, ms = entry.get("rollout_mse"), entry.get("forward_ms_per_step")
                if _finite_mean(mse) is None or _finite_mean(ms) is None:
                    continue
                ax.errorbar(ms["mean"], 1e3 * mse["mean"], xerr=_std(ms), yerr=1e3 * _std(mse), fmt="o", capsize=3,
                            label=f"{columns[key]} ({group['label']})")
        coarse = bench.get("yardsticks", {}).get("coarse_solver")
        if coarse and coarse.get("rollout_mse") and coarse.get("forward_ms_per_step"):
            ax.plot(coarse["forward_ms_per_step"], 1e3 * coarse["rollout_mse"], "k*", markersize=12, label=coarse["label"])
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):  # decades only: the minor labels of a short log axis overlap
            axis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("forward ms per step (solver: per frame)")
        ax.set_ylabel("test rollout MSE (1e-3)")
        ax.set_title(name)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    save_figure(fig, path)
    return True


def ablation_chart(paper: dict, manifest: DictConfig, path: Path) -> bool:
    """Per benchmark with ablation runs: rollout and consistency MSE of each variant, bars with std."""
    variants = dict(manifest.ablation_variants)
    panels = [(n, b) for n, b in paper["benchmarks"].items()
              if any(e["status"] == "evaluated" for e in b.get("ablation", {}).values())]
    if not panels:
        return False
    fig, axes = plt.subplots(len(panels), 2, figsize=(11, 3.8 * len(panels)), squeeze=False)
    for row, (name, bench) in zip(axes, panels):
        for ax, key, title in zip(row, ("rollout_mse", "consistency_mse"), ("test rollout MSE", "consistency MSE")):
            for i, (variant, label) in enumerate(variants.items()):
                stats = bench["ablation"][variant].get(key)
                if _finite_mean(stats) is not None:
                    ax.bar(i, 1e3 * stats["mean"], 0.7, yerr=1e3 * _std(stats), capsize=3)
                    ax.text(i, 1e3 * stats["mean"], f"n={stats['n']}", ha="center", va="bottom", fontsize=7)
                else:
                    ax.text(i, 0, NOT_TRAINED, rotation=90, ha="center", va="bottom", fontsize=7, color="grey")
            ax.set_xticks(range(len(variants)), list(variants.values()), rotation=30)
            ax.set_ylabel(f"{title} (1e-3)")
            ax.set_title(f"{name}: {title}")
    save_figure(fig, path)
    return True


# ------------------------------------------------------------------------------------------- main

def write(paper: dict, manifest: DictConfig, out: Path) -> list[str]:
    out.mkdir(parents=True, exist_ok=True)
    charts = [name for name, make in (("rollout_mse.png", rollout_chart), ("accuracy_vs_speed.png", speed_chart),
                                      ("ablation.png", ablation_chart)) if make(paper, manifest, out / name)]
    paper["charts"] = charts
    write_whole(out / "paper.json", (json.dumps(paper, indent=2, default=str) + "\n").encode())
    write_whole(out / "tables.md", render(paper, manifest, charts).encode())
    return charts


def read_manifest(argv: list[str] | None, usage: str) -> tuple[DictConfig, list[str]]:
    """The command line of a command over ``conf/paper.yaml`` (``rgns.paper``, ``rgns.failures``):
    ``usage`` printed for -h / --help, logging set up, and the manifest with the overrides
    (Hydra syntax; a bad one ends the command with one line naming it); and the arguments."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if {"-h", "--help"} & set(argv):
        print(usage)
        raise SystemExit(0)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    try:
        return compose_config("paper", argv), argv
    except HydraException as error:
        raise SystemExit(f"error: conf/paper.yaml: {' '.join(str(error).split())}") from None


def main(argv: list[str] | None = None) -> dict:
    """``python -m rgns.paper [key=value ...]``: the manifest's overrides (Hydra syntax)."""
    manifest, argv = read_manifest(argv, __doc__)
    paper = build(manifest, argv)
    out = Path(manifest.out_dir)
    write(paper, manifest, out)
    log.info("wrote %s, %s and %d chart(s)", out / "tables.md", out / "paper.json", len(paper["charts"]))
    return paper


if __name__ == "__main__":
    main()
