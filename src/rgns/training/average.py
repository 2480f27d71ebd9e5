"""Uniform weight averages of checkpoints: the "model soup" of runs fine-tuned from one file.

``python -m rgns.training.average OUT CKPT CKPT [CKPT ...]`` writes ``OUT``, a checkpoint whose
weights are the mean of the given checkpoints' (their ``state_dict``: with weight averaging in
training, the averaged weights each run validated and saved). Runs that share a start file and a
small learning rate tend to stay in one basin, where their mean can score better than each; the
average is only worth keeping where the scores say so (docs/recipe_study.md).

``OUT`` must not exist (``--overwrite`` to replace it) and is never one of the inputs: a
forgotten output argument would otherwise write the mean over the first checkpoint. ``OUT``
loads wherever a trained checkpoint does (``evaluate.py ckpt_paths=[OUT]``, ``init_from=OUT``);
it holds no optimiser state, so it cannot be resumed. Every input must be an
rgns checkpoint of the same model (the same ``model`` config and the same parameter names and
shapes); a mismatch is refused naming the file, and ``OUT`` is written whole or not at all.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from rgns.data.contract import atomic_path
from rgns.training.module import _NOT_A_CHECKPOINT, CheckpointError, _read_checkpoint


def average_checkpoints(paths: list[str]) -> dict:
    """The checkpoint dict whose ``state_dict`` is the mean of those of ``paths`` (floating
    tensors averaged in float64, then cast back; integer buffers must agree); the rest is the
    first file's, less its optimiser and scheduler states and its weights before averaging in
    training (``current_model_state``), plus ``averaged_from: paths``.

    Raises :class:`CheckpointError` naming the file that is unreadable or differs from the first."""
    if len(paths) < 2:
        raise ValueError(f"averaging needs at least two checkpoints, got {len(paths)}")
    first = _read_checkpoint(paths[0], "checkpoint to average")
    config = _model_config(first)
    if config is None:
        raise CheckpointError(f"{paths[0]}: {_NOT_A_CHECKPOINT}")
    reference = first["state_dict"]
    total = {name: value.double() for name, value in reference.items() if value.is_floating_point()}
    for path in paths[1:]:
        other = _read_checkpoint(path, "checkpoint to average")
        if _model_config(other) != config:
            raise CheckpointError(f"{path}: another model than {paths[0]}'s ({_model_config(other)} against {config}): "
                                  "only runs of one model can be averaged")
        weights = other["state_dict"]
        if weights.keys() != reference.keys():
            names = sorted(set(weights) ^ set(reference))[:5]
            raise CheckpointError(f"{path}: its weights are not named as {paths[0]}'s (e.g. {names})")
        for name, value in weights.items():
            if value.shape != reference[name].shape:
                raise CheckpointError(f"{path}: {name} has shape {tuple(value.shape)}, {paths[0]}'s "
                                      f"{tuple(reference[name].shape)}")
            if name in total:
                total[name] += value.double()
            elif not torch.equal(value, reference[name]):
                raise CheckpointError(f"{path}: its {name} (not a weight: an integer buffer) differs from {paths[0]}'s")
    averaged = dict(first)
    averaged["state_dict"] = {name: (total[name] / len(paths)).to(value.dtype) if name in total else value
                              for name, value in reference.items()}
    for key in ("optimizer_states", "lr_schedulers", "current_model_state"):
        averaged.pop(key, None)
    averaged["averaged_from"] = [str(path) for path in paths]
    return averaged


def _model_config(checkpoint: dict):
    """The ``model`` config a checkpoint was trained with, or ``None`` where it has none."""
    hparams = checkpoint.get("hyper_parameters")
    return hparams.get("model") if isinstance(hparams, dict) else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rgns.training.average", description=__doc__.split("\n\n")[0])
    parser.add_argument("out", help="the averaged checkpoint to write")
    parser.add_argument("checkpoints", nargs="+", help="two or more checkpoints of one model")
    parser.add_argument("--overwrite", action="store_true", help="write over OUT if it exists (never over an input)")
    args = parser.parse_args(argv)
    out = Path(args.out).resolve()
    if any(Path(path).resolve() == out for path in args.checkpoints):
        parser.error(f"{args.out} is OUT and also one of the checkpoints to average: it would be written over; "
                     "give the output first, as a new file")
    if out.exists() and not args.overwrite:
        parser.error(f"{args.out} exists (OUT, the first argument, is the file written: was the output "
                     "forgotten?); refused, so as not to write over it. Give a new file, or --overwrite")
    try:
        averaged = average_checkpoints(args.checkpoints)
    except (CheckpointError, FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    with atomic_path(args.out) as tmp:
        torch.save(averaged, tmp)
    print(f"{args.out}: the mean of {len(args.checkpoints)} checkpoints' weights")
    return 0


if __name__ == "__main__":
    sys.exit(main())
