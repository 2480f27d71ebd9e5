"""Train a simulator: ``python train.py [overrides]``; sweeps with ``-m``, e.g.
``python train.py -m loss=dl1,dl2,dl3,dl4``. Returns the best validation loss (for sweepers).

``init_from=<checkpoint>`` starts from a checkpoint's weights with a fresh optimiser, schedule and
step count (a fine-tune, e.g. a longer schedule for a finished run); with ``init_grow=true`` the
model may be deeper than the checkpoint's (R-GNS: the added reversible blocks start as the
identity, so the run starts from the checkpoint's predictions); ``resume=`` continues a run.

Every run ends with ``checkpoints/last.ckpt``; one stopped by SIGTERM or Ctrl-C finishes its step,
saves it, says where it is and exits with 143 / 130 (rgns.training.checkpointing). A run folder
holding an earlier run's checkpoints is refused unless ``resume=`` continues one of them or
``overwrite=true`` is given (rgns.runs); a bad dataset, checkpoint or option is one line, exit 1."""
from __future__ import annotations

import sys

import hydra
import lightning as L
from hydra.utils import instantiate
from omegaconf import DictConfig

from rgns.runs import refusals_in_one_line, register_resolvers
from rgns.training.checkpointing import LastCheckpoint, StopOnSignal
from rgns.training.ddp import ddp_job
from rgns.training.module import check_resume, warm_start


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
@refusals_in_one_line  # a bad dataset, checkpoint or option: one line naming it, exit 1
def main(cfg: DictConfig) -> float | None:
    L.seed_everything(cfg.seed, workers=True)

    datamodule = instantiate(cfg.data)
    datamodule.prepare_data()
    module = instantiate(cfg.module, model=cfg.model, loss=cfg.loss, metadata=datamodule.metadata, _recursive_=False)
    # read with .get: `~init_from` (or `~resume`, `~init_grow`) removes the key, which means "not set"
    init_from, resume, init_grow = cfg.get("init_from"), cfg.get("resume"), cfg.get("init_grow", False)
    if init_from:
        if resume:
            raise ValueError("init_from and resume both set: resume= continues a run (its optimiser, schedule and "
                             "step), init_from= starts a new one from a checkpoint's weights; give one")
        warm_start(module, init_from, grow=init_grow)
    elif init_grow:
        raise ValueError("init_grow=true grows the model of init_from=<checkpoint>: set init_from")
    if resume:  # refused here, by name, rather than deep inside Lightning
        check_resume(module, resume)
    trainer = instantiate(
        cfg.trainer,
        logger=instantiate(cfg.logger),
        callbacks=[instantiate(c) for c in cfg.callbacks.values() if c is not None],  # `callbacks.X=null` drops one
    )
    with ddp_job():
        trainer.fit(module, datamodule=datamodule, ckpt_path=resume)
    stopped_by = next((c.received for c in trainer.callbacks if isinstance(c, StopOnSignal) and c.received), None)
    if stopped_by is not None:
        last = next((c.path(trainer) for c in trainer.callbacks if isinstance(c, LastCheckpoint)), None)
        print(f"stopped by {stopped_by.name} at step {trainer.global_step}; latest state: {last} "
              f"(continue with resume={last})", file=sys.stderr, flush=True)
        sys.exit(128 + stopped_by.value)

    best = trainer.checkpoint_callback.best_model_score
    return None if best is None else float(best)


if __name__ == "__main__":
    register_resolvers()  # ${rgns_fresh:...}: a run folder of its own
    main()
