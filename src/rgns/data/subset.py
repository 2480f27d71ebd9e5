"""A dataset holding some trajectories of another's split: ``python -m rgns.data.subset SRC DST``.

Command line::

    python -m rgns.data.subset datasets/waterdrop_select32 datasets/waterdrop_judge16 --split test --trajectories 16:32

``--trajectories`` takes Python-style ranges and single numbers, joined by commas (``16:32``,
``0,3,5``, ``0:8,12``). The new folder holds those trajectories of ``--split`` renumbered from
``00000`` in the order given, and the source's other splits as they are. Its ``metadata.json`` is
the source's with

- ``subset`` = ``{source, split, trajectories}``: where the trajectories came from;
- ``generator.draws`` = ``{split: [...]}`` (generated datasets only): the generator's draw number
  of each stored trajectory, so that the dataset's solver re-run (the evaluation's solver
  references) redraws the right initial states, as it does on the source;
- for a subset of the train split, the normalisation statistics, ``num_particles_max`` and
  ``regime`` recomputed from the new train split (a model trained on the subset normalises by
  what it sees).

The folder appears whole or not at all (written beside ``DST`` and renamed); an existing ``DST``
is never touched.
"""
from __future__ import annotations

import argparse
import copy
import os
import shutil
import tempfile
from pathlib import Path
from typing import Sequence

from rgns.data.contract import (SPLITS, DatasetError, Split, dataset_folder, read_metadata, split_path, write_metadata,
                                write_split)
from rgns.data.stats import compute_statistics, regime_summary


def parse_trajectories(text: str, count: int) -> list[int]:
    """``"16:32"``, ``"0,3,5"`` or ``"0:8,12"`` as a list of indices into a split of ``count``
    trajectories; raises ``ValueError`` naming the part that is malformed, out of range or repeated."""
    indices: list[int] = []
    for part in text.split(","):
        bounds = part.strip().split(":")
        try:
            numbers = [int(x) for x in bounds]
        except ValueError:
            numbers = []
        if len(numbers) == 1 and 0 <= numbers[0] < count:
            indices.append(numbers[0])
        elif len(numbers) == 2 and 0 <= numbers[0] < numbers[1] <= count:
            indices += range(*numbers)
        else:
            raise ValueError(f"--trajectories: {part.strip()!r} is neither a trajectory number nor a range START:STOP "
                             f"with 0 <= START < STOP <= {count} (the split has {count} trajectories)")
    _refuse_repeats(indices, f"--trajectories: {text!r} names trajectories")
    return indices


def _refuse_repeats(indices: list[int], what: str) -> None:
    """A ``ValueError`` that starts with ``what`` when an index comes more than once (a subset holds
    each trajectory once)."""
    repeated = sorted({i for i in indices if indices.count(i) > 1})
    if repeated:
        raise ValueError(f"{what} {repeated} more than once (a subset holds each trajectory once)")


def make_subset(source: str | os.PathLike, target: str | os.PathLike, split: str,
                trajectories: Sequence[int] | str) -> Path:
    """Write ``target``: ``source`` with only ``trajectories`` (indices, or the command line's text)
    of ``split``. See the module docs. Returns the target's path."""
    source, target = dataset_folder(source), Path(target)
    if split not in SPLITS:
        raise ValueError(f"--split: unknown split {split!r}; the splits are {list(SPLITS)}")
    if target.exists():
        raise DatasetError(f"{target}: already exists; choose another folder or delete it")
    metadata = read_metadata(source)
    with Split(split_path(source, split), dim=metadata["dim"]) as data:
        if isinstance(trajectories, str):
            trajectories = parse_trajectories(trajectories, len(data))
        trajectories = [int(i) for i in trajectories]
        if not trajectories:
            raise ValueError("--trajectories: no trajectory chosen")
        out_of_range = [i for i in trajectories if not 0 <= i < len(data)]
        if out_of_range:
            raise DatasetError(f"{source / f'{split}.h5'}: has {len(data)} trajectories; no trajectory {out_of_range}")
        _refuse_repeats(trajectories, f"trajectories {trajectories}: index")
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
        try:
            write_split(staging / f"{split}.h5", (data[i] for i in trajectories))
            for other in SPLITS:
                if other != split:
                    shutil.copyfile(split_path(source, other), staging / f"{other}.h5")
            write_metadata(staging, _subset_metadata(metadata, source, staging, split, trajectories))
            os.rename(staging, target)  # fails, keeping the staged folder out of the way, if target appeared meanwhile
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return target


def _subset_metadata(metadata: dict, source: Path, staging: Path, split: str, trajectories: list[int]) -> dict:
    metadata = copy.deepcopy(metadata)
    metadata["subset"] = {"source": str(source), "split": split, "trajectories": trajectories}
    generator = metadata.get("generator")
    if isinstance(generator, dict):
        draws = (generator.get("draws") or {}).get(split)  # a subset of a subset keeps the first draws
        generator.setdefault("draws", {})[split] = [draws[i] for i in trajectories] if draws else trajectories
    shapes = []
    for name in SPLITS:
        with Split(staging / f"{name}.h5", dim=metadata["dim"]) as data:
            shapes += data.shapes
            if name == split == "train":  # what depends on the training trajectories
                metadata.update(compute_statistics(data))
                if "regime" in metadata:
                    metadata["regime"] = regime_summary(data, float(metadata["default_connectivity_radius"]))
    metadata["num_particles_max"] = max(shape[1] for shape in shapes)
    return metadata


def main(argv: Sequence[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(prog="python -m rgns.data.subset", description=__doc__.split("\n\n")[0])
    parser.add_argument("source", help="the dataset folder to take trajectories from")
    parser.add_argument("target", help="the new dataset folder (must not exist)")
    parser.add_argument("--split", default="test", choices=SPLITS, help="the split to take a subset of (default: test)")
    parser.add_argument("--trajectories", required=True, help="e.g. 16:32, 0,3,5 or 0:8,12")
    args = parser.parse_args(argv)
    path = make_subset(args.source, args.target, args.split, args.trajectories)
    print(f"{path}: trajectories {args.trajectories} of {args.source}'s {args.split} split")
    return path


if __name__ == "__main__":
    main()
