"""Evaluate trained simulators on a dataset's test split: ``python evaluate.py ckpt_path=...``,
``ckpt_paths=[a,b]`` or ``checkpoints_dir=<multirun folder>``; ``task=forward|inverse|all``.

Writes ``results.json``, ``report.md`` (the paper's tables), charts and animations to the run
folder, whole or not at all; until the evaluation has finished the folder holds an ``INCOMPLETE``
file, which stays if it is stopped (SIGTERM: exit 143, Ctrl-C: 130, with a message) or fails. A
folder holding an earlier evaluation is refused unless ``overwrite=true``. Returns the first
method's rollout MSE (for sweepers), if a forward task ran.
"""
from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from rgns.evaluation.run import INCOMPLETE, evaluate
from rgns.runs import Stopped, refusals_in_one_line, register_resolvers, signals_stop


@hydra.main(version_base="1.3", config_path="conf", config_name="evaluate")
@refusals_in_one_line  # a bad dataset, checkpoint or option: one line naming it, exit 1
def main(cfg: DictConfig) -> float | None:
    try:
        with signals_stop():
            results = evaluate(cfg)
    except Stopped as stop:  # the folder keeps its INCOMPLETE marker: what it holds is not an evaluation
        print(f"evaluate.py stopped by {stop}: {cfg.output_dir} is incomplete (see its {INCOMPLETE}); run the "
              "command again to evaluate", file=sys.stderr, flush=True)
        sys.exit(128 + stop.signum)
    first = next(iter(results["datasets"].values()))
    return next((row["rollout_mse"] for row in first["summary"].values() if row.get("rollout_mse") is not None), None)


if __name__ == "__main__":
    register_resolvers()  # ${rgns_fresh:...}: an output folder of its own
    main()
