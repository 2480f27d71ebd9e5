"""Where a run's time goes, and a progress line for logs that are not a terminal."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import lightning as L


class TimeSplit(L.Callback):
    """Measures a ``fit``'s wall time spent in optimisation steps, in validation and elsewhere
    (data loading, checkpointing, logging), writes it to ``<dirpath>/timing.json`` at the end of
    the fit and prints it. When the output is not a terminal (a log file, a scheduler), it also
    prints a progress line every ``every_s`` seconds: step, loss, steps per second, time left.

    Args:
        dirpath: where ``timing.json`` goes (the run folder); ``None``: the trainer's
            ``default_root_dir``.
        every_s: seconds between two progress lines; ``0`` never prints them.
        force_lines: print progress lines even on a terminal.
    """

    def __init__(self, dirpath: str | None = None, every_s: float = 30.0, force_lines: bool = False):
        self.dirpath, self.every_s = dirpath, every_s
        self.lines = every_s > 0 and (force_lines or not sys.stderr.isatty())
        self.steps_s = self.validation_s = 0.0
        self.steps = 0
        self._fit_start = self._batch_start = self._val_start = self._last_line = None

    # -- the clocks ------------------------------------------------------------------------------
    def on_fit_start(self, trainer, pl_module) -> None:
        self._fit_start = self._last_line = time.perf_counter()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._batch_start = time.perf_counter()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        now = time.perf_counter()
        if self._batch_start is not None:
            self.steps_s += now - self._batch_start
            self.steps += 1
        if self.lines and now - self._last_line >= self.every_s and trainer.global_rank == 0:
            self._last_line = now
            self._print_line(trainer, outputs, now)

    def on_validation_start(self, trainer, pl_module) -> None:
        self._val_start = time.perf_counter()

    def on_validation_end(self, trainer, pl_module) -> None:
        if self._val_start is not None and not trainer.sanity_checking:
            self.validation_s += time.perf_counter() - self._val_start
        self._val_start = None
        if self.lines and trainer.global_rank == 0 and not trainer.sanity_checking:
            shown = {k: float(v) for k, v in trainer.callback_metrics.items()
                     if k.startswith("val/") and k in ("val/loss", "val/rollout_mse", "val/consistency_mse")}
            print(f"[validation] step {trainer.global_step}: "
                  + ", ".join(f"{k} {v:.4g}" for k, v in sorted(shown.items())), file=sys.stderr, flush=True)

    def on_fit_end(self, trainer, pl_module) -> None:
        if self._fit_start is None or trainer.global_rank != 0:
            return
        split = self.summary()
        folder = Path(self.dirpath or trainer.default_root_dir)
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "timing.json").write_text(json.dumps(split, indent=2))
        print(f"[time] {split['fit_s']:.0f} s in fit: {split['steps']} optimisation steps "
              f"{split['steps_s']:.0f} s ({100 * split['steps_fraction']:.0f}%, {split['steps_per_s']:.1f} steps/s), "
              f"validation {split['validation_s']:.0f} s, other {split['other_s']:.0f} s -> {folder / 'timing.json'}",
              file=sys.stderr, flush=True)

    # -- reporting -------------------------------------------------------------------------------
    def summary(self) -> dict:
        fit = time.perf_counter() - self._fit_start
        return {
            "fit_s": fit,
            "steps": self.steps,
            "steps_s": self.steps_s,
            "validation_s": self.validation_s,
            "other_s": max(fit - self.steps_s - self.validation_s, 0.0),
            "steps_fraction": self.steps_s / fit if fit > 0 else 0.0,
            "steps_per_s": self.steps / self.steps_s if self.steps_s > 0 else 0.0,
        }

    def _print_line(self, trainer, outputs, now: float) -> None:
        loss = outputs.get("loss") if isinstance(outputs, dict) else outputs
        loss = float(loss) if loss is not None else float("nan")
        rate = self.steps / self.steps_s if self.steps_s > 0 else 0.0
        elapsed = now - self._fit_start
        total = trainer.max_steps if trainer.max_steps and trainer.max_steps > 0 else None
        left = ""
        if total and self.steps:  # the rate of this fit's own steps: a resumed run starts past step 0
            left = f", ~{(total - trainer.global_step) * elapsed / self.steps / 60:.1f} min left"
        print(f"[train] step {trainer.global_step}{f'/{total}' if total else ''}: loss {loss:.4g}, "
              f"{rate:.1f} steps/s in steps, {elapsed / 60:.1f} min{left}", file=sys.stderr, flush=True)
