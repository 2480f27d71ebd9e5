"""Run folders that no two runs share.

``hydra.run.dir: ${rgns_fresh:runs/${now:%Y-%m-%d_%H-%M-%S}}`` names a run by the second it
started, like Hydra's default, and claims the folder by creating it: ``os.mkdir`` fails for every
process but one, so a second run started in the same second (a script launching several, a
scheduler's array job) takes ``<name>_2``, the next ``<name>_3``, and so on. The claim is made
once per process and name, so every copy of the config a process resolves points to one folder.
An explicit ``hydra.run.dir=...`` is used as given.

``train.py`` and ``evaluate.py`` register the resolver before Hydra composes their config; an
application composing ``rgns.conf`` with its Hydra settings calls :func:`register_resolvers` first.
"""
from __future__ import annotations

import functools
import os
import shutil
import signal
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from hydra.experimental.callback import Callback
from omegaconf import OmegaConf

_claimed: dict[str, str] = {}


def claim_run_dir(base: str) -> str:
    """``base``, or ``base_2``, ``base_3``...: the first that this call could create."""
    if base not in _claimed:
        Path(base).parent.mkdir(parents=True, exist_ok=True)
        for n in range(1, 10_000):
            candidate = base if n == 1 else f"{base}_{n}"
            try:
                os.mkdir(candidate)
            except FileExistsError:
                continue
            _claimed[base] = candidate
            break
        else:
            raise RuntimeError(f"could not claim a run folder: {base} and 9,999 numbered variants exist")
    return _claimed[base]


def register_resolvers() -> None:
    """Register ``${rgns_fresh:...}`` (:func:`claim_run_dir`) with OmegaConf, once."""
    if not OmegaConf.has_resolver("rgns_fresh"):
        OmegaConf.register_new_resolver("rgns_fresh", claim_run_dir)


# -- refusals: one line, nothing left behind ----------------------------------------------------

class Stopped(BaseException):
    """SIGTERM or SIGINT reached a command that stops cleanly on them (``signals_stop``). A
    ``BaseException``, so that no ``except Exception`` on the way swallows it."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_received: list[int] = []  # the signal signals_stop caught, while within it


@contextmanager
def signals_stop() -> Iterator[None]:
    """Within: SIGTERM and SIGINT raise :class:`Stopped` in the main thread (the handlers from
    before are restored after). Raised at an arbitrary point, it can be turned into another
    exception by the code it interrupts (a ``finally`` that fails on half-changed state) or
    swallowed by it: whatever ends the block after a signal, the block raises :class:`Stopped`,
    and :func:`stop_received` says so to the code inside, which must not report itself finished."""
    def handler(signum, frame):
        if not _received:
            _received.append(signum)
            raise Stopped(signum)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    except BaseException as err:
        if _received and not isinstance(err, Stopped):
            raise Stopped(_received[0]) from err
        raise
    else:
        unless_stopped()
    finally:
        _received.clear()
        for s, h in previous.items():
            signal.signal(s, h)


def stop_received() -> int | None:
    """The signal :func:`signals_stop` has caught, if any (``None`` outside it)."""
    return _received[0] if _received else None


def unless_stopped() -> None:
    """Raise :class:`Stopped` again if :func:`signals_stop` has caught a signal whose exception
    was swallowed on the way (raised inside a ``__del__`` or a weakref callback, Python only
    prints it): called before writing outputs, so that nothing is written after a signal."""
    if _received:
        raise Stopped(_received[0])


def _refusal(err: BaseException) -> BaseException | None:
    """The rgns refusal behind ``err`` (itself, or the cause Hydra's ``instantiate`` wrapped), if any."""
    from rgns.data.contract import DatasetError
    from rgns.errors import ConfigError
    from rgns.targets import UnsafeConfigError
    from rgns.training.module import CheckpointError

    kinds = (CheckpointError, DatasetError, ConfigError, UnsafeConfigError, FileNotFoundError)
    seen = 0
    while err is not None and seen < 10:
        if isinstance(err, kinds):
            return err
        err, seen = err.__cause__ or err.__context__, seen + 1
    return None


def refusals_in_one_line(task):
    """Wrap a Hydra task function: a refusal (bad data, checkpoint or option) is
    printed as one line, ``error: <message>``, and exits with status 1; a run folder this
    process claimed for it (``rgns_fresh``) and that holds nothing but Hydra's own files (and
    an evaluation's ``INCOMPLETE`` marker) is removed, so a refused run leaves no empty folder.
    Other errors go on to Hydra as before."""
    @functools.wraps(task)
    def wrapper(cfg):
        try:
            return task(cfg)
        except Exception as err:
            refusal = _refusal(err)
            if refusal is None:
                raise
            _discard_claimed_folders()
            message = " ".join(str(refusal).split()) if isinstance(refusal, FileNotFoundError) else str(refusal)
            print(f"error: {message}", file=sys.stderr, flush=True)
            sys.exit(1)
    return wrapper


def _discard_claimed_folders() -> None:
    for folder in map(Path, _claimed.values()):
        if folder.is_dir() and all(p.name in (".hydra", "INCOMPLETE") or p.suffix == ".log" for p in folder.iterdir()):
            shutil.rmtree(folder, ignore_errors=True)


class KeepEarlierResults(Callback):
    """Hydra callback: refuse, before Hydra writes anything, a run whose folder
    (``hydra.run.dir`` given by hand, or a sweep's ``hydra.sweep.dir``) holds an earlier run's
    results: checkpoints for ``kind: train`` (unless ``resume=`` continues a checkpoint of that
    very folder), anything at all for ``kind: evaluate``. ``overwrite=true`` on the command line
    removes those results first and lets the run go on, so a folder never mixes two runs'
    results."""

    def __init__(self, kind: str):
        if kind not in ("train", "evaluate"):
            raise ValueError(f"kind must be 'train' or 'evaluate', got {kind!r}")
        self.kind = kind

    def on_run_start(self, config, **kwargs) -> None:
        self._check(Path(str(config.hydra.run.dir)), config, sweep=False)

    def on_multirun_start(self, config, **kwargs) -> None:
        self._check(Path(str(config.hydra.sweep.dir)), config, sweep=True)

    def _check(self, folder: Path, config, sweep: bool) -> None:
        if not folder.is_dir():
            return
        overwrite = bool(config.get("overwrite", False))
        if self.kind == "train":
            pattern = "*/checkpoints/*.ckpt" if sweep else "checkpoints/*.ckpt"
            found = sorted(folder.glob(pattern))
            resume = config.get("resume")
            own = resume and Path(str(resume)).resolve().parent == (folder / "checkpoints").resolve()
            if found and not sweep and own:
                return  # resume= of this folder's own checkpoint: the run goes on where it was
            what = "checkpoints of an earlier run"
            hint = "resume=<its last.ckpt> to continue that run there, "
        else:
            found = sorted(folder.iterdir())
            what = "an earlier evaluation's files"
            hint = ""
        if not found:
            return
        if overwrite:
            for path in found:  # removed first: the folder never mixes the earlier results with the new
                shutil.rmtree(path) if path.is_dir() else path.unlink()
            print(f"overwrite=true: removed {len(found)} of {what} from {folder} ({found[0].name}"
                  f"{', ...' if len(found) > 1 else ''})", file=sys.stderr, flush=True)
            return
        shown = ", ".join(str(p.relative_to(folder)) for p in found[:3]) + (", ..." if len(found) > 3 else "")
        print(f"error: {folder}: holds {what} ({shown}); refused, so as not to write over them. Choose another "
              f"hydra.{'sweep' if sweep else 'run'}.dir, {hint}or add overwrite=true", file=sys.stderr, flush=True)
        sys.exit(1)
