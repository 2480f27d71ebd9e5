"""Nothing lost: checkpoints written whole, a checkpoint at the end of every fit, and a signal
(SIGTERM from a scheduler, Ctrl-C) that stops training at the next step boundary instead of
killing it mid-step.

- :class:`AtomicCheckpointIO` writes each checkpoint to ``<name>.partial`` and renames it into
  place: a kill during the write leaves the previous file as it was.
- :class:`LastCheckpoint` is ``last.ckpt``: written at every validation (like a
  ``ModelCheckpoint`` without a monitor), every ``every_minutes`` of training (10 by default: a
  kill no process can catch loses at most that), and again when training ends, whatever ended it
  (max steps, max time, early stopping, a signal), so the latest state is never lost.
- :class:`StopOnSignal` turns SIGINT and SIGTERM into a stop after the running step; the ranks of a
  DDP run agree on the step. ``train.py`` then says where the checkpoint is and exits with
  ``128 + signal`` (130, 143), as a process killed by it would, so a scheduler sees the failure.
  A second Ctrl-C interrupts at once.
"""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.plugins.io import TorchCheckpointIO


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's ``torch.save`` checkpoint IO, through a ``.partial`` file and ``os.replace``."""

    def save_checkpoint(self, checkpoint, path, storage_options=None) -> None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(path.name + ".partial")
        try:
            super().save_checkpoint(checkpoint, partial, storage_options)
        except BaseException:
            partial.unlink(missing_ok=True)
            raise
        os.replace(partial, path)  # atomic on one file system: readers see the old file or the new


class LastCheckpoint(ModelCheckpoint):
    """``<dirpath>/last.ckpt``: the latest state, saved at validations and at the end of training.

    Lightning's ``save_last`` follows new best checkpoints only, and a ``ModelCheckpoint`` saves at
    validations only: a run stopped between two (or before the first) kept nothing of its last
    steps. Training stopped by an exception (a non-finite loss, a crash) saves nothing more: the
    state it stopped in is not one to resume from.
    """

    #: steps between two looks at the clock (the same steps on every rank)
    CLOCK_EVERY = 20

    def __init__(self, dirpath: str | None = None, filename: str = "last",
                 every_minutes: float | None = 10.0):
        super().__init__(dirpath=dirpath, filename=filename, monitor=None, save_top_k=1,
                         enable_version_counter=False)
        if every_minutes is not None and every_minutes <= 0:
            raise ValueError(f"callbacks.last.every_minutes must be positive or null, got {every_minutes}")
        self.every_minutes = every_minutes
        self._saved_at = time.monotonic()

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_start(trainer, pl_module)
        self._saved_at = time.monotonic()

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        """Also save every ``every_minutes`` of training, so that a run killed without a signal it
        can catch (the machine taken away) loses at most that much; rank 0's clock decides."""
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        if self.every_minutes is None or trainer.global_step % self.CLOCK_EVERY:
            return
        due = time.monotonic() - self._saved_at >= 60.0 * self.every_minutes
        if trainer.strategy.broadcast(due) and self._last_global_step_saved != trainer.global_step:
            self._save_checkpoint(trainer, self.path(trainer))

    def _save_checkpoint(self, trainer: L.Trainer, filepath: str) -> None:
        super()._save_checkpoint(trainer, filepath)
        self._saved_at = time.monotonic()

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_end(trainer, pl_module)
        if trainer.global_step > 0 and self._last_global_step_saved != trainer.global_step:
            self._save_checkpoint(trainer, self.path(trainer))

    def path(self, trainer: L.Trainer) -> str:
        """Where ``last.ckpt`` goes (the same name at every save)."""
        return self.format_checkpoint_name(self._monitor_candidates(trainer))


class StopOnSignal(L.Callback):
    """SIGINT / SIGTERM during training: finish the running step, end training (so
    :class:`LastCheckpoint` saves), and record the signal in ``received`` for ``train.py``."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.received: signal.Signals | None = None
        self._previous: dict[int, object] = {}

    def _handler(self, signum, frame) -> None:
        self.received = signal.Signals(signum)
        if signum == signal.SIGINT:  # a second Ctrl-C: interrupt now, as without this callback
            signal.signal(signal.SIGINT, signal.default_int_handler)

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # before the DataLoader workers are forked: they inherit it, and a Ctrl-C to the whole
        # process group no longer kills them under the batch the main process is receiving
        self._install()

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # again after Lightning's own SIGTERM handler (registered after on_fit_start), which it
        # replaces: Lightning's raises an exception at the step boundary, bypassing the end of training
        self._install()

    def _install(self) -> None:
        for signum in self.SIGNALS:
            previous = signal.signal(signum, self._handler)
            self._previous.setdefault(signum, previous)  # the handlers from before the fit

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        # every rank stops after the same step (a rank leaving alone would hang the others)
        if trainer.strategy.reduce_boolean_decision(self.received is not None, all=False):
            if self.received is None:
                self.received = signal.SIGTERM  # another rank's
            trainer.should_stop = True

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._restore()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._restore()

    def _restore(self) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
        self._previous.clear()
