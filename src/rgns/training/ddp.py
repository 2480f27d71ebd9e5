"""DDP under Hydra multiruns.

Lightning's subprocess launcher starts ranks 1..n-1 by re-running ``sys.argv`` with
``hydra.run.dir`` set to ``HydraConfig.run.dir``. Under ``-m`` that would re-run the whole sweep
in every child, in run folders of their own. :func:`ddp_job` points both at the current job
instead (the job's own overrides, without ``-m``, and the job's own output folder), and after the
job tears down what the launcher left in this process (the process group and the
``LOCAL_RANK``/``MASTER_PORT``... variables), so that the next job of the sweep launches its own
ranks instead of taking itself for a child.
"""
from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from typing import Iterator

import torch.distributed as dist
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import read_write


@contextmanager
def ddp_job() -> Iterator[None]:
    multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    argv, environ = list(sys.argv), dict(os.environ)
    if multirun:
        hydra_cfg = HydraConfig.get()
        sys.argv = [sys.argv[0], *hydra_cfg.overrides.task]
        with read_write(hydra_cfg):
            hydra_cfg.run.dir = hydra_cfg.runtime.output_dir
    try:
        yield
    finally:
        if multirun:
            if dist.is_available() and dist.is_initialized():
                dist.destroy_process_group()
            sys.argv = argv
            os.environ.clear()
            os.environ.update(environ)
