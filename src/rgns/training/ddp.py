"""DDP under Hydra multiruns.

Lightning's subprocess launcher starts ranks 1..n-1 by re-running ``sys.argv`` with
``hydra.run.dir`` set to ``HydraConfig.run.dir``. Under ``-m`` that re-runs the whole sweep in
every child, in run folders of their own. Before the trainer launches, this points both at the
current job instead: the job's own overrides (no ``-m``) and the job's own output folder.
"""
from __future__ import annotations

import sys

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import read_write


def pin_ddp_children_to_this_job() -> None:
    if not HydraConfig.initialized():
        return
    hydra_cfg = HydraConfig.get()
    if hydra_cfg.mode != RunMode.MULTIRUN:
        return
    sys.argv = [sys.argv[0], *hydra_cfg.overrides.task]
    with read_write(hydra_cfg):
        hydra_cfg.run.dir = hydra_cfg.runtime.output_dir
