"""Where methods fail, across benchmarks, by one command: ``python -m rgns.failures [key=value ...]``
(``bash scripts/generalise.sh``; docs/generalise.md).

The manifest is ``conf/paper.yaml``: its benchmarks (each a test dataset and sets of checkpoints)
and its section ``generalise``, which names the set and the methods to roll out and the settings
of ``evaluate.py task=generalise`` (:class:`rgns.evaluation.generalise.Generalisation`). Per
benchmark:

- the training-free baselines (constant velocity, ballistic with walls) and the dataset's solver at
  a coarser grid, on every condition, once (the yardsticks);
- every run of the chosen methods (one checkpoint a seed) on the same conditions, one evaluation
  each (``task=generalise``, no baselines beside it);
- the conditions generated once per benchmark and settings, in a folder the evaluations share.

Every evaluation is cached as :mod:`rgns.paper`'s are (keyed by the checkpoint's content, the
dataset's and the settings): a rerun evaluates only what is new, and a stopped run loses only the
evaluation it was in. Out, in ``generalise.out_dir``: ``generalise.md`` (per benchmark, each method's
rollout MSE on each condition as mean ± std over its runs, how many runs broke and the earliest
break; then backwards in time), ``generalise.json`` (every number and the evaluation it came from)
and ``generalise.png`` (a panel per benchmark).
"""
from __future__ import annotations

import json
import logging
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from rgns.evaluation.generalise import Generalisation, condition_scene
from rgns.evaluation.methods import build_baselines
from rgns.evaluation.plots import save_figure, write_whole
from rgns.evaluation.report import GAP, span, table
from rgns.evaluation.run import evaluate
from rgns.evaluation.tasks import Dataset
from rgns.paper import (NOT_TRAINED, Cache, cell, compose_config, data_hash, find_runs, flatten, missing_dataset,
                        override_value, read_manifest, statistics)
from rgns.training.stages import sha256

import matplotlib.pyplot as plt  # noqa: E402 - after rgns.evaluation.plots has chosen the Agg backend

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------ the settings

def task_settings(manifest: DictConfig, name: str) -> dict:
    """``generalise.task`` with the benchmark's own changes (``generalise.benchmarks.<name>``)."""
    settings = OmegaConf.to_container(manifest.generalise.task, resolve=True)
    own = (manifest.generalise.get("benchmarks") or {}).get(name)
    if own:
        settings.update(OmegaConf.to_container(own, resolve=True))
    unknown = set(settings) - {"conditions", "trajectories", "steps", "seed", "rule", "directions", "inverse_conditions"}
    if unknown:
        raise ValueError(f"conf/paper.yaml: generalise.task / generalise.benchmarks.{name}: unknown key(s) "
                         f"{sorted(unknown)}")
    return settings


def checkpoint_config(manifest: DictConfig, checkpoint: str, root: str, out: str, settings: dict,
                      conditions: str) -> DictConfig:
    """``evaluate.py task=generalise`` for one checkpoint alone: no baselines, no references
    (the yardsticks are measured once per benchmark), the conditions generated in ``conditions``."""
    overrides = ["task=generalise", f"data_root={override_value(root)}", f"output_dir={override_value(out)}",
                 f"ckpt_path={override_value(checkpoint)}", "without_hard_walls=false",
                 f"start={override_value(manifest.evaluate.start)}", "animation.max_frames=2",
                 *flatten({"task": {"generalise": settings}}), "task.generalise.references=null",
                 f"task.generalise.conditions_dir={override_value(conditions)}"]
    cfg = compose_config("evaluate", overrides)
    cfg.baselines, cfg.references = None, None
    return cfg


def settings_key(root: str, settings: dict, manifest: DictConfig) -> dict:
    return dict(data=data_hash(root, "test"), start=manifest.evaluate.start, settings=settings)


# ------------------------------------------------------------------------------------- evaluations

def one_by_one(settings: dict) -> list[tuple[str, dict]]:
    """Each condition's settings alone (backwards too where ``inverse_conditions`` names it): one
    evaluation, and one cache entry, per condition, so that a condition added later, or a run
    stopped mid-way, costs only the conditions not yet evaluated."""
    backwards = settings.get("inverse_conditions") or []
    return [(c, dict(settings, conditions=[c], inverse_conditions=[c] if c in backwards else []))
            for c in settings.get("conditions") or []]


def conditions_folder(cache: Cache, root: str, settings: dict, manifest: DictConfig) -> str:
    """One folder per dataset and generation settings, shared by the benchmark's evaluations (a
    ``<dataset>_<condition>`` dataset in it per condition)."""
    generation = {k: settings.get(k) for k in ("trajectories", "steps", "seed")}
    key = Cache.key(dict(kind="conditions", **settings_key(root, generation, manifest)))
    return str((cache.folder / "conditions" / key).resolve())


def run_results(checkpoint: str, root: str, settings: dict, manifest: DictConfig, cache: Cache,
                conditions: str) -> tuple[dict, dict]:
    """``results.json`` of one checkpoint's ``task=generalise`` on ``root`` (from the cache when
    there), and where it came from."""
    material = dict(kind="generalise", checkpoint=sha256(checkpoint), **settings_key(root, settings, manifest))

    def make(folder: Path) -> None:
        log.info("generalise: %s on %s", checkpoint, root)
        evaluate(checkpoint_config(manifest, checkpoint, root, str(folder), settings, conditions))

    return cache.obtain(material, "results.json", make, dict(material, first_path=checkpoint))


def yardstick_results(root: str, settings: dict, manifest: DictConfig, cache: Cache,
                      conditions: str) -> tuple[dict, dict]:
    """The training-free baselines and the solver at a coarser grid (``generalise.references``) on
    every condition: the ``generalise`` section they make."""
    references = OmegaConf.to_container(manifest.generalise.references, resolve=True)
    history = int(manifest.history)
    material = dict(kind="generalise_yardsticks", history=history, references=references,
                    **settings_key(root, settings, manifest))

    def make(folder: Path) -> None:
        import torch

        log.info("generalise: yardsticks on %s", root)
        torch.set_num_threads(1)
        cfg = compose_config("evaluate", [])
        dataset = Dataset.load(root, "test", 1, history, int(manifest.evaluate.start), "cpu")
        baselines = build_baselines(cfg.baselines, dataset.metadata, history, "cpu")
        task = Generalisation(str(folder), references=references, conditions_dir=conditions, **settings)
        section, _ = task(baselines, dataset)
        write_whole(folder / "generalise.json", (json.dumps(section, indent=2) + "\n").encode())

    return cache.obtain(material, "generalise.json", make)


def generalise_section(results: dict, where: str) -> tuple[str, dict, dict]:
    """The one trained method of an evaluation's ``results.json``: its label, seed and section."""
    (label,) = [label for label, info in results["methods"].items() if info.get("source") not in ("baseline", "reference")]
    (data,) = results["datasets"].values()
    if "generalise" not in data:
        raise ValueError(f"{where}: no generalise section")
    return label, results["methods"][label], data["generalise"]


# -------------------------------------------------------------------------------- runs and numbers

def summarise_runs(rows: list[dict | None]) -> dict | None:
    """One method on one condition and direction over its runs: rollout MSE statistics, the runs
    that broke and the earliest break."""
    rows = [r for r in rows if r is not None]
    if not rows:
        return None
    mses = [r["rollout_mse"] for r in rows if r.get("rollout_mse") is not None and np.isfinite(r["rollout_mse"])]
    broke = [r["first_break"] for r in rows if r.get("first_break")]
    return dict(rollout_mse=statistics(mses) if mses else None, runs=len(rows), non_finite=len(rows) - len(mses),
                broke=len(broke), earliest=min(broke, key=lambda b: (b["step"], b["cause"])) if broke else None,
                stable_steps=[r["stable_steps"] for r in rows], steps=max(r["steps"] for r in rows))


def benchmark(name: str, spec: DictConfig, manifest: DictConfig, cache: Cache) -> dict:
    """The yardsticks and every run of the chosen methods on every condition of one benchmark."""
    g = manifest.generalise
    root = str(spec.data)
    out = dict(data=root, set=g.set, methods={}, evaluations=[])
    missing = missing_dataset(spec)
    if missing:
        out.update(status=NOT_TRAINED, reason=missing)
        return out
    settings = task_settings(manifest, name)
    generator = json.loads((Path(root) / "metadata.json").read_text()).get("generator")
    if not isinstance(generator, dict) or not isinstance(generator.get("params"), dict):
        out.update(status="not evaluated", reason=f"{root}/metadata.json names no generator (a converted dataset?): "
                   "no scene to change")
        return out
    start = int(manifest.evaluate.start)
    out.update(status="evaluated", settings=settings, start=start)
    conditions = conditions_folder(cache, root, settings, manifest)
    sections = {}  # method key -> [(label, section)], a run each
    out["yardsticks"] = dict(conditions={}, errors=[])
    chosen = []
    for condition, alone in one_by_one(settings):  # a condition the scene cannot have is named, not evaluated
        scene, what = condition_scene(condition, generator["params"], int(settings["steps"]), start)
        if scene is None:
            out["yardsticks"]["conditions"][condition] = dict(skipped=what)
        else:
            chosen.append((condition, alone))
    for condition, alone in chosen:
        try:
            section, where = yardstick_results(root, alone, manifest, cache, conditions)
            out["evaluations"].append(dict(yardsticks=True, condition=condition, **where))
            out["yardsticks"]["conditions"].update(section["conditions"])
        except Exception as error:  # noqa: BLE001 - reported, not a crash
            log.warning("%s: yardsticks not measured on %s (%s: %s)", name, condition, type(error).__name__, error)
            out["yardsticks"]["errors"].append(f"{condition}: {type(error).__name__}: {error}")
    group = (spec.get("sets") or {}).get(g.set) or {}
    for key in g.methods:
        patterns = (group.get("methods") or {}).get(key)
        runs = [r for r in find_runs(patterns) if "checkpoint" in r]
        entry = out["methods"][key] = dict(label=manifest.methods.get(key) or manifest.inverse_methods.get(key) or key,
                                           runs=[], failed=[])
        if not runs:
            entry.update(status=NOT_TRAINED, reason=f"no checkpoint matches {', '.join(map(str, patterns or []))}"
                         if patterns else f"set {g.set} lists no {key}")
            continue
        for run in runs:
            merged, label, info, caches = dict(conditions={}), None, {}, []
            for condition, alone in chosen:
                try:
                    results, where = run_results(run["checkpoint"], root, alone, manifest, cache, conditions)
                    label, info, section = generalise_section(results, run["checkpoint"])
                except Exception as error:  # noqa: BLE001 - one run that fails is named, the others reported
                    log.warning("%s on %s: not evaluated (%s: %s)", run["checkpoint"], condition,
                                type(error).__name__, error)
                    entry["failed"].append(f"{run['checkpoint']} on {condition}: {type(error).__name__}: {error}")
                    continue
                out["evaluations"].append(dict(checkpoint=run["checkpoint"], condition=condition, **where))
                merged["conditions"].update(section["conditions"])
                caches.append(where["cache"])
            if label is None:
                continue
            entry["runs"].append(dict(checkpoint=run["checkpoint"], label=label, seed=info.get("seed"), caches=caches))
            sections.setdefault(key, []).append((label, merged))
        entry["status"] = "evaluated" if entry["runs"] else "not evaluated"
        if not entry["runs"]:
            entry["reason"] = "; ".join(entry["failed"])
        entry["models"] = sorted({r["label"] for r in entry["runs"]})
        entry["seeds"] = [r["seed"] for r in entry["runs"]]
    out["conditions"] = conditions_table(out, sections)
    return out


def conditions_table(out: dict, sections: dict) -> dict:
    """Per condition: what it is, and per direction each method's :func:`summarise_runs` (the
    yardsticks under their own labels); backwards, the methods without an inverse by name."""
    yard = out.get("yardsticks", {}).get("conditions", {})
    found = [*yard, *(c for runs in sections.values() for _, s in runs for c in s["conditions"])]
    order = out["settings"]["conditions"]
    names = sorted(dict.fromkeys(found), key=lambda c: order.index(c) if c in order else len(order))
    table_ = {}
    for c in names:
        first = yard.get(c) or next((s["conditions"][c] for runs in sections.values() for _, s in runs
                                     if c in s["conditions"]), {})
        entry = table_[c] = dict(description=first.get("description") or first.get("skipped"),
                                 skipped="skipped" in first, particles=first.get("particles"),
                                 forward={}, inverse={}, without_inverse={})
        for key, runs in sections.items():
            rows = [s["conditions"].get(c, {}) for _, s in runs]
            entry["forward"][key] = summarise_runs([r.get("methods", {}).get(label) for (label, _), r in zip(runs, rows)])
            backward = [r.get("inverse") for r in rows]
            if any(b is not None for b in backward):
                without = [b["without_inverse"].get(label) for (label, _), b in zip(runs, backward) if b]
                if any(without):
                    entry["without_inverse"][key] = next(w for w in without if w)
                else:
                    entry["inverse"][key] = summarise_runs([b["methods"].get(label) if b else None
                                                            for (label, _), b in zip(runs, backward)])
        for label, row in (yard.get(c) or {}).get("methods", {}).items():
            entry["forward"][label] = summarise_runs([row])
        for label, row in ((yard.get(c) or {}).get("inverse") or {}).get("methods", {}).items():
            entry["inverse"][label] = summarise_runs([row])
        for label, why in ((yard.get(c) or {}).get("inverse") or {}).get("without_inverse", {}).items():
            entry["without_inverse"][label] = why
        if not any(entry["forward"].values()):
            entry["forward"] = {}
    return table_


# ----------------------------------------------------------------------------------------- tables

def run_cell(summary: dict | None) -> str:
    """``mean ± std (n)`` in 1e-3, then ``none broke`` or ``k of n broke, first: cause at step``."""
    if summary is None:
        return GAP
    n = summary["runs"]
    mse = cell(summary["rollout_mse"], 1e3) if summary["rollout_mse"] else "non-finite"
    if n == 1:
        mse = mse.removesuffix(" (1)")
    if summary["non_finite"] and summary["rollout_mse"]:
        mse += f", {summary['non_finite']} non-finite"
    if not summary["broke"]:
        return f"{mse}; {'none broke in' if n > 1 else 'held'} {summary['steps']} steps"
    first = summary["earliest"]
    broke = "broke" if n == 1 else f"{summary['broke']} of {n} broke"
    return f"{mse}; {broke}, first: {first['cause']} at {first['step']}"


def label_of(key: str, entry: dict | None) -> str:
    if entry is None:  # a yardstick: its own label
        return key
    models = ", ".join(entry.get("models") or []) or entry["label"]
    return f"{entry['label']} ({models}; {len(entry['runs'])} run{'' if len(entry['runs']) == 1 else 's'})"


def benchmark_lines(name: str, bench: dict) -> list[str]:
    out = ["", f"## {name}", ""]
    if bench["status"] != "evaluated":
        return out + [f"{NOT_TRAINED}: {bench['reason']}"]
    s = bench["settings"]
    conditions = bench["conditions"]
    ran = [c for c, e in conditions.items() if e["forward"]]
    out += [f"Set `{bench['set']}`; {s.get('trajectories')} trajector{'y' if s.get('trajectories') == 1 else 'ies'} per condition, {s.get('steps')} steps from frame "
            f"{bench['start']}, generated with seed {s.get('seed')}. Conditions:", ""]
    out += [f"- {c}: {e['description']}" + (f" ({span(e['particles'])} particles)" if e.get("particles") else "")
            for c, e in conditions.items()]
    keys = list(dict.fromkeys(k for c in ran for k in conditions[c]["forward"]))
    rows = [[label_of(k, bench["methods"].get(k)), *(run_cell(conditions[c]["forward"].get(k)) for c in ran)] for k in keys]
    if rows:
        out += ["", table(["Method", *ran], rows)]
    backwards = [c for c, e in conditions.items() if e["inverse"] or e["without_inverse"]]
    if backwards:
        keys = list(dict.fromkeys(k for c in backwards for k in [*conditions[c]["inverse"], *conditions[c]["without_inverse"]]))
        rows = [[label_of(k, bench["methods"].get(k)),
                 *("no inverse" if k in conditions[c]["without_inverse"] else run_cell(conditions[c]["inverse"].get(k))
                   for c in backwards)] for k in keys]
        out += ["", f"Backwards in time ({s.get('steps')} inverse steps from each trajectory's last frame):", "",
                table(["Method", *backwards], rows)]
    missing = [f"{e['label']}: {e['status']} ({e['reason']})" for e in bench["methods"].values() if e.get("reason")]
    failed = [f for e in bench["methods"].values() for f in e.get("failed", [])]
    missing += [f"yardsticks on {e}" for e in bench.get("yardsticks", {}).get("errors", [])]
    out += ["", *(f"- {m}" for m in missing + failed)] if missing or failed else []
    out += ["", f"Each of the {len(bench['evaluations'])} evaluations (a run, or the yardsticks, on one condition) keeps "
            "its report.md, results.json and break pictures in its cache folder, listed in generalise.json "
            f"(`benchmarks.{name}.evaluations`)."]
    return out


def render(paper: dict) -> str:
    lines = ["# Where methods fail, across benchmarks", "",
             f"Reproduce with: `{paper['command']}` (run {paper['date']}).", "",
             "Cells: rollout MSE (1e-3) over the condition's steps, mean ± sample std over the method's runs (n), "
             "then whether any run broke (a NaN, a particle out of the box, exploded, compressed or stalled: "
             "rgns.evaluation.generalise.classify_break) and the earliest break over runs and trajectories. "
             "A yardstick is one run."]
    for name, bench in paper["benchmarks"].items():
        lines += benchmark_lines(name, bench)
    lines += ["", "![Rollout MSE on each condition](generalise.png)"] if paper.get("chart") else []
    return "\n".join(lines) + "\n"


def chart(paper: dict, path: Path) -> bool:
    """A panel per benchmark: each method's rollout MSE per condition (bars, log scale, std), an
    ``x`` over a bar where a run broke."""
    panels = [(n, b) for n, b in paper["benchmarks"].items()
              if b["status"] == "evaluated" and any(e["forward"] for e in b["conditions"].values())]
    if not panels:
        return False
    fig, axes = plt.subplots(len(panels), 1, figsize=(11, 3.6 * len(panels)), squeeze=False)
    for ax, (name, bench) in zip(axes[:, 0], panels):
        ran = [c for c, e in bench["conditions"].items() if e["forward"]]
        keys = list(dict.fromkeys(k for c in ran for k in bench["conditions"][c]["forward"]))
        width = 0.8 / max(len(keys), 1)
        for m, key in enumerate(keys):
            for i, c in enumerate(ran):
                summary = bench["conditions"][c]["forward"].get(key)
                if not summary or not summary["rollout_mse"]:
                    continue
                x = i + (m - (len(keys) - 1) / 2) * width
                stats = summary["rollout_mse"]
                ax.bar(x, 1e3 * stats["mean"], width, yerr=1e3 * (stats.get("std") or 0.0), capsize=2,
                       color=f"C{m}", label=label_of(key, bench["methods"].get(key)) if i == 0 else None)
                if summary["broke"]:
                    ax.plot(x, 1e3 * stats["mean"] * 1.4, "kx")
        ax.set_xticks(range(len(ran)), ran)
        ax.set_yscale("log")
        ax.set_ylabel("rollout MSE (1e-3)")
        ax.set_title(f"{name}: x = at least one run broke")
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    save_figure(fig, path)
    return True


# ------------------------------------------------------------------------------------------- main

def main(argv: list[str] | None = None) -> dict:
    """``python -m rgns.failures [key=value ...]``: conf/paper.yaml's overrides (Hydra syntax)."""
    manifest, argv = read_manifest(argv, __doc__)
    g = manifest.generalise
    cache = Cache(manifest.cache_dir, bool(manifest.refresh))
    chosen = list(g.only) if g.get("only") else list(manifest.benchmarks)
    unknown = [b for b in chosen if b not in manifest.benchmarks]
    if unknown:
        raise SystemExit(f"error: conf/paper.yaml: generalise.only names {unknown}; benchmarks: "
                         f"{', '.join(manifest.benchmarks)}")
    paper = dict(command=" ".join(["python -m rgns.failures", *argv]),
                 date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                 generalise=OmegaConf.to_container(g, resolve=True), benchmarks={})
    for name in chosen:
        paper["benchmarks"][name] = benchmark(name, manifest.benchmarks[name], manifest, cache)
    out = Path(g.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paper["chart"] = chart(paper, out / "generalise.png")
    write_whole(out / "generalise.json", (json.dumps(paper, indent=2, default=str) + "\n").encode())
    write_whole(out / "generalise.md", render(paper).encode())
    log.info("wrote %s and %s", out / "generalise.md", out / "generalise.json")
    return paper


if __name__ == "__main__":
    main()
