"""DDP under Hydra multiruns, and a watchdog for ranks that die (:class:`RankWatchdog`).

Lightning's subprocess launcher starts ranks 1..n-1 by re-running ``sys.argv`` with
``hydra.run.dir`` set to ``HydraConfig.run.dir``. Under ``-m`` that would re-run the whole sweep
in every child, in run folders of their own. :func:`ddp_job` points both at the current job
instead (the job's own overrides, without ``-m``, and the job's own output folder), and after the
job tears down what the launcher left in this process (the process group and the
``LOCAL_RANK``/``MASTER_PORT``... variables), so that the next job of the sweep launches its own
ranks instead of taking itself for a child.
"""
from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path
from typing import Iterator

import lightning as L
import torch.distributed as dist
from lightning.pytorch.strategies import DDPStrategy
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


class RankWatchdog(L.Callback):
    """A DDP run whose rank dies stops, within seconds and with a message, instead of waiting.

    A rank that dies leaves the others inside a collective (a gradient all-reduce, a barrier),
    where they wait for the process group's timeout (30 minutes) or for ever. In a run launched by
    Lightning's subprocess launcher (``trainer=ddp_sim``, ``trainer=ddp`` on one node), rank 0 polls
    the ranks it started every ``poll_s`` seconds; one that exits with an error or a signal while
    the fit runs, or with status 0 and rank 0 still in the fit ``grace_s`` seconds later, ends the
    run: rank 0 prints which rank, how it ended and the last lines of its log, stops the other ranks
    and exits with status 1. The other ranks watch rank 0 the same way (their parent process) and
    exit with status 1 when it is gone. Runs of one process, and ranks started by an outside
    launcher (torchrun, SLURM), are left alone: their launcher watches them.
    """

    def __init__(self, poll_s: float = 1.0, grace_s: float = 60.0):
        self.poll_s, self.grace_s = poll_s, grace_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._procs: list[subprocess.Popen] = []
        self._folder = Path(".")

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if trainer.world_size < 2 or self._thread is not None:
            return
        procs = list(getattr(getattr(trainer.strategy, "launcher", None), "procs", None) or [])
        folder = Path(trainer.default_root_dir or ".")
        if trainer.global_rank == 0 and procs:
            self._procs, self._folder = procs, folder
            target = functools.partial(self._watch_ranks, procs, folder)
        elif trainer.local_rank > 0 and os.environ.get("LOCAL_RANK") and not os.environ.get("TORCHELASTIC_RUN_ID"):
            target = functools.partial(self._watch_parent, os.getppid(), trainer.global_rank)
        else:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=target, name="rank-watchdog", daemon=True)
        self._thread.start()

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        self._stop.set()
        self._thread = None

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        # a collective that fails at once (gloo sees the dead peer's socket close) ends the fit with
        # an exception before the next poll: name the rank that caused it before it propagates
        deadline = time.monotonic() + 3.0
        while self._procs and time.monotonic() < deadline:
            dead = [(rank, proc) for rank, proc in enumerate(self._procs, start=1) if proc.poll() not in (None, 0)]
            if dead:
                self._stop.set()
                for rank, proc in dead:
                    print(f"error: {_ended(rank, proc)}; the {type(exception).__name__} below in rank 0 follows "
                          f"from it. {_last_words(self._folder / f'train_ddp_process_{rank}.log')}",
                          file=sys.stderr, flush=True)
                return
            time.sleep(0.1)

    def _watch_ranks(self, procs: list[subprocess.Popen], folder: Path) -> None:
        ended_at: dict[int, float] = {}
        while not self._stop.wait(self.poll_s):
            for rank, proc in enumerate(procs, start=1):
                code = proc.poll()
                if code is None:
                    continue
                ended_at.setdefault(rank, time.monotonic())
                if code == 0 and time.monotonic() - ended_at[rank] < self.grace_s:
                    continue  # a rank that finished cleanly: rank 0 is about to finish too
                if self._stop.is_set():
                    return
                self._abort(f"{_ended(rank, proc)}; the run cannot go on without it. "
                            f"{_last_words(folder / f'train_ddp_process_{rank}.log')}", procs)

    def _watch_parent(self, parent: int, rank: int) -> None:
        while not self._stop.wait(self.poll_s):
            if os.getppid() != parent:
                self._abort(f"DDP rank {rank}: rank 0 (pid {parent}), which started it, is gone; rank {rank} "
                            "stops too", [])

    @staticmethod
    def _abort(message: str, procs: list[subprocess.Popen]) -> None:
        print(f"error: {message}", file=sys.stderr, flush=True)
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
        os._exit(1)  # this process's main thread may be blocked in a collective: no clean way out


def _ended(rank: int, proc: subprocess.Popen) -> str:
    code = proc.returncode
    how = f"was killed by {signal.Signals(-code).name}" if code < 0 else f"exited with status {code}"
    return f"DDP rank {rank} (pid {proc.pid}) {how} while rank 0 was still in the fit"


def _last_words(log: Path, lines: int = 5) -> str:
    """The last ``lines`` lines of a rank's log, or why there are none."""
    if not log.is_file():
        return f"It left no log ({log} does not exist); its output went to the terminal."
    text = log.read_text(errors="replace").strip().splitlines()[-lines:]
    if not text:
        return f"Its log, {log}, is empty: it died before logging anything (its output went to the terminal)."
    return f"The last lines of its log, {log}:\n" + "\n".join(f"  {line}" for line in text)


def ddp_strategy(timeout_s: float = 600.0, **kwargs) -> DDPStrategy:
    """Lightning's DDP strategy with a process-group timeout of ``timeout_s`` seconds (torch's
    default is 30 minutes): a rank that never joins, or a collective that a rank never reaches,
    ends the run with an error within that time instead of after half an hour. The longest
    legitimate wait in rgns's training is a checkpoint write or a validation rollout on rank 0."""
    return DDPStrategy(timeout=timedelta(seconds=timeout_s), **kwargs)
