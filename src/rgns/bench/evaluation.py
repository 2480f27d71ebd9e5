"""The evaluation's forward rollouts in one process and in several, side by side:
``python -m rgns.bench evaluation [--checkpoints A B ...] [--data-root DIR] [--trajectories N]
[--workers W] [--no-references]``.

Times :class:`~rgns.evaluation.tasks.ForwardRollout` on the same methods as the main job's
evaluation (the checkpoints with their no-hard-walls twins, the training-free baselines and the
dataset's solver references, built afresh for each measurement so that neither reuses the
other's solver runs), first with one process, then with ``--workers``; checks that both give the
same results and prints the ratio of wall times.
"""
from __future__ import annotations

import argparse
import glob
import time

import torch
from omegaconf import OmegaConf

from rgns import config_dir
from rgns.evaluation.methods import build_baselines, find_checkpoints, load_checkpoints, without_hard_walls
from rgns.evaluation.references import SolverReferences
from rgns.evaluation.tasks import Dataset, ForwardRollout


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoints", nargs="+", default=sorted(glob.glob("pretrained/waterdrop40_main/*.ckpt")),
                        help="checkpoint files (default: pretrained/waterdrop40_main/*.ckpt)")
    parser.add_argument("--data-root", default="datasets/waterdrop40_main")
    parser.add_argument("--trajectories", type=int, default=8, help="the first N test trajectories")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-references", action="store_true", help="leave out the solver references")
    args = parser.parse_args(argv)
    if not args.checkpoints:
        parser.error("no checkpoints: pass --checkpoints (pretrained/waterdrop40_main/ holds none here)")
    torch.set_num_threads(1)

    baselines = OmegaConf.to_container(OmegaConf.load(config_dir() / "evaluate.yaml").baselines)
    methods = load_checkpoints(find_checkpoints(ckpt_paths=args.checkpoints))
    history = max(m.model.history for m in methods)
    dataset = Dataset.load(args.data_root, "test", args.trajectories, history, None)
    fixed = methods + without_hard_walls(methods) + build_baselines(baselines, dataset.metadata, history)
    print(f"{len(fixed)} methods ({', '.join(m.label for m in fixed)}), "
          f"{'no references' if args.no_references else 'and the solver references'}, "
          f"{len(dataset.trajectories)} trajectories x {args.steps} steps", flush=True)
    seconds, results = {}, {}
    for workers in (1, args.workers):
        references = [] if args.no_references else SolverReferences()(dataset)[0]
        task = ForwardRollout(steps=args.steps, workers=workers)
        begin = time.perf_counter()
        results[workers] = task(fixed + references, dataset)[0]
        seconds[workers] = time.perf_counter() - begin
        print(f"workers={workers}: {seconds[workers]:.1f} s", flush=True)
    same = results[1]["methods"] == results[args.workers]["methods"]
    print(f"the same results: {same}; workers={args.workers} takes {seconds[args.workers] / seconds[1]:.2f}x the time "
          f"of workers=1 ({seconds[1] / seconds[args.workers]:.2f}x as fast)")
    if not same:
        raise SystemExit("the results differ between workers=1 and workers=" + str(args.workers))
