"""One evaluation: checkpoints, baselines and solver references in, ``results.json``,
``report.md``, charts and animations out (the body of ``python evaluate.py``)."""
from __future__ import annotations

import json
import logging
import platform
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from rgns.data.contract import DatasetError, metadata_differences
from rgns.data.datamodule import at_stride
from rgns.errors import ConfigError
from rgns.evaluation import plots, report
from rgns.evaluation.methods import (build_baselines, check_fits, find_checkpoints, load_checkpoints, seed_groups,
                                     trained_on, without_hard_walls)
from rgns.evaluation.tasks import Dataset
from rgns.runs import stop_received, unless_stopped

log = logging.getLogger(__name__)
INCOMPLETE = "INCOMPLETE"  # the marker file of an evaluation that has not finished


def summarise(sections: dict) -> dict:
    """The headline numbers of each method on one dataset, from the tasks' sections: what the
    report's tables and the accuracy-against-speed chart show."""
    forward, inverse, efficiency = (sections.get(k, {}).get("methods", {}) for k in ("forward", "inverse", "efficiency"))
    table_horizon = sections.get("inverse", {}).get("settings", {}).get("table_horizon")
    summary = {}
    for label in dict.fromkeys([*forward, *inverse, *efficiency]):
        row = {}
        if label in forward:
            row.update(rollout_mse=forward[label]["rollout_mse"], stable_steps=forward[label]["stable_steps"],
                       diverged=forward[label]["diverged"], stride=forward[label].get("stride", 1),
                       rollout_mse_shared=forward[label].get("rollout_mse_shared"))
        if label in efficiency:
            cost = efficiency[label]
            row.update(parameters=cost["parameters"], forward_ms_per_step=cost["forward_ms_per_step"],
                       forward_ms_per_frame=cost.get("forward_ms_per_frame", cost["forward_ms_per_step"]),
                       stride=cost.get("stride", 1),
                       inverse_ms_per_step=cost.get("inverse_ms_per_step"), memory_mb=cost["forward_memory_mb"])
        if label in inverse:
            at = inverse[label]["horizons"][str(table_horizon)]
            row.update(consistency_mse=at["consistency_mse"], inverse_mse=at["inverse_mse"],
                       max_stable_steps=inverse[label]["max_stable_steps"],
                       stable_beyond_tested=inverse[label]["stable_beyond_tested"])
            if row.get("inverse_ms_per_step") is not None:  # as the paper: K inverse steps
                row["inverse_seconds"] = table_horizon * row["inverse_ms_per_step"] / 1e3
        summary[label] = row
    return summary


def over_seeds(summary: dict, groups: dict[str, list[str]]) -> dict:
    """Mean, standard deviation (n - 1), least and greatest of each headline number over the
    runs of a seed group (:func:`~rgns.evaluation.methods.seed_groups`) measured here."""
    out = {}
    for name, labels in groups.items():
        rows = [summary[label] for label in labels if label in summary]
        if len(rows) < 2:
            continue
        entry = {"runs": [label for label in labels if label in summary]}
        for key in ("rollout_mse", "consistency_mse", "inverse_mse"):
            values = [row.get(key) for row in rows]
            if any(v is None for v in values):
                continue
            values = np.asarray(values, dtype=float)
            entry[key] = dict(mean=float(values.mean()), std=float(values.std(ddof=1)), min=float(values.min()),
                              max=float(values.max()), values=values.tolist())
        out[name] = entry
    return out


def command_line() -> str:
    from hydra.core.hydra_config import HydraConfig

    try:
        overrides = list(HydraConfig.get().overrides.task)
    except ValueError:  # composed without @hydra.main (tests, notebooks)
        overrides = sys.argv[1:]
    return " ".join(["python evaluate.py", *overrides])


def evaluate(cfg: DictConfig) -> dict:
    torch.set_num_threads(cfg.threads)
    walls_off = cfg.get("without_hard_walls", True)
    if walls_off not in (True, False, "fresh"):
        raise ValueError(f"without_hard_walls={walls_off!r}: true, false or fresh (all but the pretrained checkpoints)")
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    marker = out / INCOMPLETE  # removed once every output is written: a stopped or failed evaluation keeps it
    marker.write_text(f"{command_line()}\nstarted {datetime.now(timezone.utc).isoformat(timespec='seconds')} and "
                      "not finished (stopped, or failed): the files here are not a whole evaluation\n")
    pretrained = find_checkpoints(ckpt_paths=cfg.pretrained) if cfg.get("pretrained") else []
    given = cfg.ckpt_path or cfg.ckpt_paths or cfg.checkpoints_dir or not pretrained
    left_out = []  # runs and checkpoints asked for but not evaluated, and why: results.json and report.md too
    checkpoints = find_checkpoints(cfg.ckpt_path, cfg.ckpt_paths, cfg.checkpoints_dir, cfg.checkpoint,
                                   left_out=left_out) if given else []
    methods = load_checkpoints(checkpoints + [p for p in pretrained if p not in checkpoints], cfg.device,
                               pretrained=pretrained, left_out=left_out)
    if cfg.get("hard_walls") is not None:  # roll every checkpoint out with (or without) hard walls
        for method in methods:
            method.model.hard_walls = bool(cfg.hard_walls)
    for method in methods:  # how each checkpoint's steps are computed: the same model, other arithmetic
        method.model.precision = cfg.get("precision", "float32")
        method.model.neighbour_skin = float(cfg.get("neighbour_skin", 0.0))
        method.model.low_precision()  # an unknown precision is refused here, before any work
    groups = seed_groups(methods)
    tasks = [instantiate(task, _convert_="all") for task in cfg.task.values() if task is not None]  # task.X=null drops X
    make_references = instantiate(cfg.references, _convert_="all") if cfg.get("references") else None  # null: none

    for task in tasks:  # a task that steps a model one frame at a time would misread a strided one
        strided = [m for m in methods if m.stride > 1]
        if strided and not getattr(task, "strided", False):
            raise ConfigError(f"task.{task.name}: {strided[0].label} ({strided[0].source}) was trained on every "
                              f"k-th frame (data.stride={strided[0].stride}), which this task does not support; "
                              f"evaluate it with task=forward, task=inverse or task=all")

    by_root: dict[str, list] = {}
    for method in methods:
        root = cfg.data_root or trained_on(method.source, method.data_root, method.data_root_relative)
        if root is None:
            raise ValueError(f"{method.source}: the checkpoint does not name its dataset; set data_root=...")
        by_root.setdefault(str(Path(root).resolve()), []).append(method)
    warnings: list[str] = []  # checkpoints scored on data other than their own: results.json and report.md
    datasets = {}  # every dataset checked, and every checkpoint against its dataset, before any task runs
    for root, trained in by_root.items():
        if cfg.start is not None:  # a start too early for a model's history (strided: k frames a velocity) is named
            for method in trained:
                method.check_start(cfg.start)
        history = max(m.first_frame() for m in trained)  # t0 leaves every model its history, at its stride
        dataset = datasets[root] = Dataset.load(root, cfg.split, cfg.trajectories, history, cfg.start, cfg.device)
        where = str(Path(root) / f"{cfg.split}.h5")
        short = [i for i, (position, _) in enumerate(dataset.trajectories) if len(position) < dataset.start + 2]
        if short:
            raise DatasetError(f"{where}: trajectories {short} have no frame after t0 = {dataset.start} (start, at "
                               f"least the {history} frames of history) to roll out to")
        for method in trained:
            check_fits(method.model, method.source, dataset.metadata, dataset.particle_types, where)
            # a strided model against the data at its stride: dt times the stride; the statistics at that
            # stride are not in metadata.json (they need a pass over the train split), so not compared
            differences = metadata_differences(method.trained_metadata or {}, at_stride(dataset.metadata, method.stride))
            if differences:  # scored all the same (a generalisation test), but never silently
                warnings.append(f"{method.source}: trained on other data than {where}: {'; '.join(differences)}")
                log.warning("%s", warnings[-1])

    results = dict(command=command_line(), date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                   config=OmegaConf.to_container(cfg, resolve=True),
                   environment=dict(torch=torch.__version__, python=platform.python_version(), device=cfg.device,
                                    threads=torch.get_num_threads()),
                   methods={m.label: dict(source=m.source, **m.info) for m in methods}, not_evaluated=left_out,
                   warnings=warnings, datasets={})
    examples = {}
    for root, trained in by_root.items():
        dataset, history = datasets[root], trained[0].model.history
        if dataset.name in results["datasets"]:  # two folders of one name (paths in sections["root"])
            dataset.name = f"{dataset.name}_{len(results['datasets']) + 1}"
        compared = trained + build_baselines(cfg.baselines, dataset.metadata, history, cfg.device)
        references, note = make_references(dataset) if make_references else ([], None)
        # the figure without the wall, beside the one with it (forward tasks, like the references)
        twinned = [m for m in trained if not m.info.get("pretrained")] if walls_off == "fresh" else (
            trained if walls_off else [])
        twins = without_hard_walls(twinned)
        log.info("%s: %d trajectories, %s", dataset.name, len(dataset.trajectories),
                 ", ".join(m.label for m in compared + twins + references))
        if note:
            log.info("%s: %s", dataset.name, note)
        sections, examples[dataset.name] = dict(root=root, split=cfg.split), {}
        for task in tasks:
            methods = compared + twins + references if getattr(task, "compares_references", False) else compared
            sections[task.name], examples[dataset.name][task.name] = task(methods, dataset)
        if make_references:
            sections["references"] = dict(settings=make_references.settings(), note=note,
                                          methods={r.label: r.describe() for r in references})
        sections["bounds"] = dataset.metadata["bounds"]
        results["datasets"][dataset.name] = sections
        for method in compared + twins + references:  # baselines, no-hard-walls twins, references
            results["methods"].setdefault(method.label, dict(source=method.source, **method.info))

    unless_stopped()  # a signal whose exception was swallowed during the tasks: nothing is written after it
    results = json.loads(json.dumps(results))  # what the file holds: str keys, no tensors
    for sections in results["datasets"].values():
        sections["summary"] = summarise(sections)
        sections["over_seeds"] = over_seeds(sections["summary"], groups)
    plots.write_whole(out / "results.json", (json.dumps(results, indent=2) + "\n").encode())
    unless_stopped()
    charts = plots.make_all(results, examples, out, cfg.animation)
    unless_stopped()
    plots.write_whole(out / "report.md", report.render(results, charts).encode())
    if stop_received() is None:  # after a signal nothing here can be trusted as whole (rgns.runs.signals_stop)
        marker.unlink()
    log.info("wrote %s", out / "report.md")
    return results
