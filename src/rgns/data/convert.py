"""Convert DeepMind's learning_to_simulate TFRecord datasets into the rgns data contract.

Usage::

    python -m rgns.data.convert SRC_DIR DST_DIR [--splits train valid test] [--overwrite]

``SRC_DIR`` holds DeepMind's ``metadata.json`` and ``train.tfrecord``, ``valid.tfrecord``,
``test.tfrecord``. Each record is a ``tf.train.SequenceExample``:

- context ``key``: int64, the trajectory's id (optional in DeepMind's reader, default 0);
- context ``particle_type``: one bytes value, int64 ``[N]`` in native (little-endian) order;
- sequence ``position``: one bytes value per frame, float32, which DeepMind's reader
  concatenates and reshapes to ``[sequence_length + 1, N, dim]``.

``DST_DIR`` receives ``metadata.json`` and one ``.h5`` per split (see :mod:`rgns.data.contract`),
trajectories in record order. DeepMind's metadata keys are kept; ``num_particles_max`` and the
conversion's provenance (``generator``, ``source``, ``version``) are added.

Records are streamed one at a time, so memory stays flat whatever the file's length (the
WaterDrop train file is 4.5 GB). Every split requested must exist: a missing one is an error,
unless it is left out with ``--splits`` (then the folder holds only the splits asked for, which
:func:`rgns.data.contract.validate_dataset` will not accept as a whole dataset). The source is
checked up front (metadata, split files, record framing) before anything is written; the output
is built in a hidden staging folder inside ``DST_DIR`` and moved into place only when every split
converted, so a failure or an interrupt leaves ``DST_DIR`` as it was.
"""
from __future__ import annotations

import argparse
import os
import shutil
import struct
import sys
import tempfile
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from tfrecord.reader import sequence_loader
from tqdm import tqdm

from rgns import __version__
from rgns.data.contract import (
    NUM_PARTICLE_TYPES,
    SPLITS,
    DatasetError,
    Trajectory,
    read_metadata,
    write_metadata,
    write_split,
)

SOURCE_FORMAT = "deepmind-learning_to_simulate-tfrecord"
_HEADER = 12  # uint64 length + uint32 masked CRC of the length
_FOOTER = 4  # uint32 masked CRC of the data


def count_records(path: Path) -> int:
    """Count the records of a TFRecord file by walking its length headers (no data is read).

    This also finds a truncated file before anything is converted.
    """
    size = path.stat().st_size
    count = offset = 0
    with open(path, "rb") as file:
        while offset < size:
            header = file.read(_HEADER)
            if len(header) < _HEADER:
                raise DatasetError(f"{path}, record {count}: truncated file (incomplete record header)")
            (length,) = struct.unpack("<Q", header[:8])
            offset += _HEADER + length + _FOOTER
            if offset > size:
                raise DatasetError(
                    f"{path}, record {count}: truncated file (a record of {length} bytes runs past "
                    f"the end of the file, {size} bytes)"
                )
            file.seek(offset)
            count += 1
    return count


def _single_bytes(value, where: str, name: str) -> bytes:
    """The one bytes value of a feature, as DeepMind stores it."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value)
    if isinstance(value, np.ndarray) and value.dtype.kind == "S":
        # The tfrecord package turns a multi-valued bytes feature into a numpy bytes array, which
        # drops trailing zero bytes: the raw data could not be recovered exactly.
        raise DatasetError(f"{where}: feature '{name}' holds {value.size} bytes values, expected one")
    raise DatasetError(f"{where}: feature '{name}' must be a bytes feature, got {type(value).__name__}")


def decode_record(context: dict, features: dict, metadata: dict, where: str) -> Trajectory:
    """Decode one parsed DeepMind record into a trajectory, checking it as DeepMind's reader would."""
    if "particle_type" not in context:
        raise DatasetError(f"{where}: context feature 'particle_type' is missing (found {sorted(context)})")
    if "position" not in features:
        raise DatasetError(f"{where}: sequence feature 'position' is missing (found {sorted(features)})")

    raw_type = _single_bytes(context["particle_type"], where, "particle_type")
    if len(raw_type) % 8:
        raise DatasetError(f"{where}: 'particle_type' has {len(raw_type)} bytes, not a whole number of int64")
    particle_type = np.frombuffer(raw_type, dtype="<i8").astype(np.int64)
    if particle_type.size == 0:
        raise DatasetError(f"{where}: 'particle_type' is empty")
    if particle_type.min() < 0 or particle_type.max() >= NUM_PARTICLE_TYPES:
        raise DatasetError(
            f"{where}: 'particle_type' holds ids outside [0, {NUM_PARTICLE_TYPES}): "
            f"{sorted(set(particle_type.tolist()))}"
        )

    steps = [_single_bytes(step, where, "position") for step in features["position"]]
    raw_position = b"".join(steps)
    del steps
    if len(raw_position) % 4:
        raise DatasetError(f"{where}: 'position' has {len(raw_position)} bytes, not a whole number of float32")
    frames, particles, dim = metadata["sequence_length"] + 1, particle_type.size, metadata["dim"]
    values = len(raw_position) // 4
    if values != frames * particles * dim:
        raise DatasetError(
            f"{where}: 'position' holds {values} float32 values, which do not reshape to "
            f"[T={frames}, N={particles}, dim={dim}] (T = sequence_length + 1 from metadata, "
            f"N = len(particle_type))"
        )
    position = np.frombuffer(raw_position, dtype="<f4").astype(np.float32, copy=False).reshape(frames, particles, dim)
    finite = np.isfinite(position).reshape(frames, -1).all(1)
    if not finite.all():
        raise DatasetError(f"{where}: 'position' holds NaN or Inf (first at frame {int(np.argmin(finite))})")
    return Trajectory(position, particle_type)


def read_tfrecord(path: Path, metadata: dict) -> Iterator[Trajectory]:
    """Stream the trajectories of one DeepMind ``.tfrecord`` file, one record at a time."""
    records = sequence_loader(str(path), None)  # no index file: read sequentially
    index = 0
    while True:
        where = f"{path}, record {index}"
        try:
            context, features = next(records)
        except StopIteration:
            return
        except Exception as err:  # framing or protobuf errors from the reader
            raise DatasetError(f"{where}: not a readable tf.train.SequenceExample ({err})") from err
        yield decode_record(context, features, metadata, where)
        index += 1


def _check_source(src: Path, splits: Sequence[str]) -> tuple[dict, dict[str, tuple[Path, int]]]:
    if not src.is_dir():
        raise DatasetError(f"{src}: source folder does not exist")
    metadata = read_metadata(src)
    length = metadata["sequence_length"]
    if not isinstance(length, int) or isinstance(length, bool) or length < 1:
        raise DatasetError(f"{src / 'metadata.json'}: 'sequence_length' must be a positive integer, got {length!r}")
    files = {}
    for split in splits:
        path = src / f"{split}.tfrecord"
        if not path.is_file():
            raise DatasetError(f"{path}: split '{split}' is missing (leave it out with --splits to convert the others)")
        files[split] = (path, count_records(path))
    return metadata, files


def _provenance(src: Path, files: dict[str, tuple[Path, int]]) -> dict:
    return {
        "generator": "rgns.data.convert",
        "source": {
            "format": SOURCE_FORMAT,
            "path": str(src.resolve()),
            "files": {split: path.name for split, (path, _) in files.items()},
        },
        "version": __version__,
    }


def convert(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    splits: Sequence[str] = SPLITS,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Convert DeepMind's dataset in ``src`` into an rgns dataset folder ``dst``; return its metadata.

    Raises :class:`DatasetError` naming the file, the record and what is wrong; ``dst`` is then
    left as it was.
    """
    src, dst = Path(src), Path(dst)
    unknown = [split for split in splits if split not in SPLITS]
    if unknown or not splits:
        raise ValueError(f"splits must be a non-empty subset of {SPLITS}, got {list(splits)}")
    metadata, files = _check_source(src, splits)

    targets = ["metadata.json", *(f"{split}.h5" for split in splits)]
    existing = [name for name in targets if (dst / name).exists()]
    if existing and not overwrite:
        raise DatasetError(f"{dst}: already holds {', '.join(existing)}; pass --overwrite to replace")

    created = not dst.exists()
    dst.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".rgns-convert-", dir=dst))
    try:
        num_particles_max, counts = 0, {}
        for split, (path, count) in files.items():

            def trajectories(path=path, count=count, split=split) -> Iterator[Trajectory]:
                nonlocal num_particles_max
                bar = tqdm(total=count, desc=f"{split}", unit="traj", disable=not progress)
                with bar:
                    for trajectory in read_tfrecord(path, metadata):
                        num_particles_max = max(num_particles_max, trajectory.particle_type.size)
                        yield trajectory
                        bar.update()

            counts[split] = write_split(staging / f"{split}.h5", trajectories())
            if counts[split] != count:  # the reader and the framing walk disagree: do not trust either
                raise DatasetError(f"{path}: read {counts[split]} records, but the file frames {count}")

        out = dict(metadata)
        out["num_particles_max"] = num_particles_max
        out.update(_provenance(src, files))
        out["source"]["trajectories"] = counts
        write_metadata(staging, out)

        for split in splits:  # metadata last: a folder with metadata is a finished folder
            os.replace(staging / f"{split}.h5", dst / f"{split}.h5")
        os.replace(staging / "metadata.json", dst / "metadata.json")
        return out
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        if created and not any(dst.iterdir()):
            dst.rmdir()


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m rgns.data.convert",
        description="Convert DeepMind's learning_to_simulate TFRecords (metadata.json, "
        "{train,valid,test}.tfrecord) into an rgns dataset folder.",
    )
    parser.add_argument("src", type=Path, help="folder with DeepMind's metadata.json and .tfrecord files")
    parser.add_argument("dst", type=Path, help="dataset folder to write")
    parser.add_argument(
        "--splits", nargs="+", choices=SPLITS, default=list(SPLITS),
        help="splits to convert (default: all three; each must exist in SRC)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace a dataset already in DST")
    args = parser.parse_args(argv)
    try:
        metadata = convert(args.src, args.dst, args.splits, overwrite=args.overwrite)
    except DatasetError as err:
        parser.exit(1, f"error: {err}\n")
    counts = ", ".join(f"{n} {split}" for split, n in metadata["source"]["trajectories"].items())
    print(f"wrote {args.dst}: {counts} trajectories, up to {metadata['num_particles_max']} particles", file=sys.stderr)


if __name__ == "__main__":
    main()
