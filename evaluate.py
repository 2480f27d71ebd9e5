"""Evaluate trained simulators on a dataset's test split: ``python evaluate.py ckpt_path=...``,
``ckpt_paths=[a,b]`` or ``checkpoints_dir=<multirun folder>``; ``task=forward|inverse|all``.

Writes ``results.json``, ``report.md`` (the paper's tables), charts and animations to the run
folder. Returns the first method's rollout MSE (for sweepers), if a forward task ran.
"""
from __future__ import annotations

import hydra
from omegaconf import DictConfig

from rgns.evaluation.run import evaluate
from rgns.runs import register_resolvers


@hydra.main(version_base="1.3", config_path="conf", config_name="evaluate")
def main(cfg: DictConfig) -> float | None:
    results = evaluate(cfg)
    first = next(iter(results["datasets"].values()))
    return next((row["rollout_mse"] for row in first["summary"].values() if row.get("rollout_mse") is not None), None)


if __name__ == "__main__":
    register_resolvers()  # ${rgns_fresh:...}: an output folder of its own
    main()
