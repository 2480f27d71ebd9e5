"""Train a simulator: ``python train.py [overrides]``; sweeps with ``-m``, e.g.
``python train.py -m loss=dl1,dl2,dl3,dl4``. Returns the best validation loss (for sweepers)."""
from __future__ import annotations

import hydra
import lightning as L
from hydra.utils import instantiate
from omegaconf import DictConfig

from rgns.training.ddp import ddp_job


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> float | None:
    L.seed_everything(cfg.seed, workers=True)

    datamodule = instantiate(cfg.data)
    datamodule.prepare_data()
    module = instantiate(cfg.module, model=cfg.model, loss=cfg.loss, metadata=datamodule.metadata, _recursive_=False)
    trainer = instantiate(
        cfg.trainer,
        logger=instantiate(cfg.logger),
        callbacks=[instantiate(c) for c in cfg.callbacks.values() if c is not None],  # `callbacks.X=null` drops one
    )
    with ddp_job():
        trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.resume)

    best = trainer.checkpoint_callback.best_model_score
    return None if best is None else float(best)


if __name__ == "__main__":
    main()
