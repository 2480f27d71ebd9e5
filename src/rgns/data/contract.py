"""The rgns data contract: how a particle dataset lies on disk.

A dataset is a folder::

    metadata.json
    train.h5  valid.h5  test.h5

Each split holds one HDF5 group per trajectory, named ``00000``, ``00001``, ..., with

- ``position``       float32 ``[T, N, D]``: particle positions, one row per frame;
- ``particle_type``  int64   ``[N]``: DeepMind's ids (5 water, 6 sand, 7 goop,
  3 static boundary, 0 rigid).

``metadata.json`` carries DeepMind's keys (``bounds``, ``sequence_length``,
``default_connectivity_radius``, ``dim``, ``dt``, ``vel_mean``, ``vel_std``, ``acc_mean``,
``acc_std``) plus what rgns adds (``num_particles_max`` and how the data was made).
Velocities and accelerations are per frame (dt = 1 in position units), as in GNS.

Kinematic particles (type 3) are conditions: never predicted, never noised, never in a loss.

Every write goes to a temporary file beside its target and is renamed over it, so an
interrupted write never leaves a half-written file where a good one was.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple

import h5py
import numpy as np

from rgns.physics.materials import GOOP, KINEMATIC, NUM_PARTICLE_TYPES, RIGID, SAND, WATER  # noqa: F401 (re-exported)

SPLITS = ("train", "valid", "test")
REQUIRED_KEYS = (
    "bounds",
    "sequence_length",
    "default_connectivity_radius",
    "dim",
    "dt",
    "vel_mean",
    "vel_std",
    "acc_mean",
    "acc_std",
)


class DatasetError(ValueError):
    """A dataset file breaks the contract; the message names the file and what is wrong."""


class Trajectory(NamedTuple):
    position: np.ndarray  # [T, N, D] float32
    particle_type: np.ndarray  # [N] int64


@contextmanager
def atomic_path(target: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; rename it over ``target`` only on success."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o666 & ~umask)  # mkstemp makes 0600; the final file gets the usual permissions
    try:
        yield tmp
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


def dataset_folder(folder: str | os.PathLike) -> Path:
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: dataset folder does not exist")
    return folder


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _is_integer(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_values(path: Path, metadata: dict) -> None:
    """Types and ranges of the keys the code reads, each error naming the key and what it expected."""
    def fail(key: str, expected: str) -> None:
        value = metadata[key]
        raise DatasetError(f"{path}: key '{key}' must be {expected}, got {value!r} ({type(value).__name__})")

    dim = metadata["dim"]
    if not _is_integer(dim) or dim not in (2, 3):
        raise DatasetError(f"{path}: key 'dim' must be 2 or 3, got {dim!r}")
    for key in ("bounds", "vel_mean", "vel_std", "acc_mean", "acc_std"):
        if not isinstance(metadata[key], list):
            what = "[low, high] rows" if key == "bounds" else "numbers"
            raise DatasetError(f"{path}: key '{key}' must be a list of {dim} {what}, got {metadata[key]!r}")
    for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        if len(metadata[key]) != dim:
            raise DatasetError(f"{path}: key '{key}' has {len(metadata[key])} entries, 'dim' is {dim}")
    if len(metadata["bounds"]) != dim:
        raise DatasetError(f"{path}: key 'bounds' has {len(metadata['bounds'])} rows, 'dim' is {dim}")
    if not all(isinstance(row, list) and len(row) == 2 and all(map(_is_number, row)) and row[0] < row[1]
               for row in metadata["bounds"]):
        fail("bounds", f"{dim} rows [low, high] of numbers with low < high")
    if not _is_integer(metadata["sequence_length"]) or metadata["sequence_length"] < 1:
        fail("sequence_length", "a positive integer (frames per trajectory - 1)")
    for key in ("default_connectivity_radius", "dt"):
        if not _is_number(metadata[key]) or metadata[key] <= 0:
            fail(key, "a positive number")
    for key in ("vel_mean", "acc_mean"):
        if not all(map(_is_number, metadata[key])):
            fail(key, f"a list of {dim} finite numbers")
    for key in ("vel_std", "acc_std"):  # 0 where nothing moves along an axis (the models add the noise std)
        if not all(_is_number(v) and v >= 0 for v in metadata[key]):
            fail(key, f"a list of {dim} numbers >= 0")
    if "num_particles_max" in metadata and not (_is_integer(metadata["num_particles_max"])
                                                and metadata["num_particles_max"] >= 1):
        fail("num_particles_max", "a positive integer")
    if "gravity" in metadata and not (isinstance(metadata["gravity"], list) and len(metadata["gravity"]) == dim
                                      and all(map(_is_number, metadata["gravity"]))):
        fail("gravity", f"a list of {dim} numbers")


def read_metadata(folder: str | os.PathLike) -> dict:
    """Read and check ``metadata.json`` of a dataset folder: every key present, of its type and range."""
    path = dataset_folder(folder) / "metadata.json"
    if not path.is_file():
        raise DatasetError(f"{path}: metadata file is missing")
    try:
        metadata = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DatasetError(f"{path}: not valid JSON ({err})") from None
    if not isinstance(metadata, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(metadata).__name__}")
    missing = [key for key in REQUIRED_KEYS if key not in metadata]
    if missing:
        raise DatasetError(f"{path}: missing key(s) {', '.join(missing)}")
    _check_values(path, metadata)
    return metadata


def write_metadata(folder: str | os.PathLike, metadata: dict) -> None:
    missing = [key for key in REQUIRED_KEYS if key not in metadata]
    if missing:
        raise DatasetError(f"{folder}: metadata to write lacks key(s) {', '.join(missing)}")
    with atomic_path(Path(folder) / "metadata.json") as tmp:
        tmp.write_text(json.dumps(metadata, indent=2, sort_keys=True) + "\n")


def split_path(folder: str | os.PathLike, split: str) -> Path:
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    path = dataset_folder(folder) / f"{split}.h5"
    if not path.is_file():
        raise DatasetError(f"{path}: split '{split}' is missing")
    return path


def write_split(path: str | os.PathLike, trajectories: Iterable[Trajectory | tuple]) -> int:
    """Write trajectories (streamed, one at a time) to one split file, atomically.

    Returns the number of trajectories written.
    """
    count = 0
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as h5:
            for position, particle_type in trajectories:
                position = np.asarray(position, dtype=np.float32)
                particle_type = np.asarray(particle_type, dtype=np.int64)
                if position.ndim != 3 or particle_type.shape != (position.shape[1],):
                    raise DatasetError(
                        f"{path}: trajectory {count:05d} has position {position.shape} and "
                        f"particle_type {particle_type.shape}; expected [T, N, D] and [N]"
                    )
                group = h5.create_group(f"{count:05d}")
                group.create_dataset("position", data=position)
                group.create_dataset("particle_type", data=particle_type)
                count += 1
    return count


class Split:
    """Read-only view of one split file, checked against the contract when opened.

    Shapes and dtypes of every trajectory are checked on open (cheap: HDF5 headers only);
    values (NaN, Inf) are checked when a trajectory is read.

    Args:
        path: the ``.h5`` file.
        dim: the dataset's dimension from metadata; positions must agree.
        min_frames: the fewest frames a trajectory may have (a training window's length).
    """

    def __init__(self, path: str | os.PathLike, dim: int | None = None, min_frames: int = 1):
        self.path = Path(path)
        if not self.path.is_file():
            raise DatasetError(f"{self.path}: file is missing")
        try:
            self._h5 = h5py.File(self.path, "r")
        except OSError as err:
            raise DatasetError(f"{self.path}: not a readable HDF5 file ({err})") from None
        try:
            self.keys = sorted(self._h5.keys())
            self.shapes = [self._check(key, dim, min_frames) for key in self.keys]
        except Exception:
            self._h5.close()
            raise

    def _where(self, key: str) -> str:
        return f"{self.path}, trajectory '{key}'"

    def _check(self, key: str, dim: int | None, min_frames: int) -> tuple[int, int, int]:
        group = self._h5[key]
        if not isinstance(group, h5py.Group) or "position" not in group or "particle_type" not in group:
            raise DatasetError(f"{self._where(key)}: needs datasets 'position' and 'particle_type'")
        position, particle_type = group["position"], group["particle_type"]
        if position.ndim != 3:
            raise DatasetError(f"{self._where(key)}: 'position' must be 3-D [T, N, D], got shape {position.shape}")
        if position.dtype.kind != "f":
            raise DatasetError(f"{self._where(key)}: 'position' must be float, got {position.dtype}")
        frames, particles, pos_dim = position.shape
        if dim is not None and pos_dim != dim:
            raise DatasetError(f"{self._where(key)}: 'position' has D={pos_dim} but metadata 'dim' is {dim}")
        if particle_type.shape != (particles,):
            raise DatasetError(
                f"{self._where(key)}: 'particle_type' has shape {particle_type.shape}, expected ({particles},)"
            )
        if particle_type.dtype.kind not in "iu":
            raise DatasetError(f"{self._where(key)}: 'particle_type' must be integer, got {particle_type.dtype}")
        if frames < min_frames:
            raise DatasetError(f"{self._where(key)}: {frames} frames, fewer than the {min_frames} a window needs")
        return frames, particles, pos_dim

    def __len__(self) -> int:
        return len(self.keys)

    def __getitem__(self, index: int) -> Trajectory:
        key = self.keys[index]
        group = self._h5[key]
        try:
            position = np.asarray(group["position"][()], dtype=np.float32)
            particle_type = np.asarray(group["particle_type"][()], dtype=np.int64)
        except OSError as err:
            raise DatasetError(f"{self._where(key)}: cannot be read, the file may be truncated ({err})") from None
        if not np.isfinite(position).all():
            frame = int(np.nonzero(~np.isfinite(position).reshape(len(position), -1).all(1))[0][0])
            raise DatasetError(f"{self._where(key)}: 'position' holds NaN or Inf (first at frame {frame})")
        unknown = np.setdiff1d(particle_type, np.arange(NUM_PARTICLE_TYPES))
        if len(unknown):
            raise DatasetError(f"{self._where(key)}: 'particle_type' holds {unknown.tolist()}, not DeepMind ids "
                               f"0..{NUM_PARTICLE_TYPES - 1} (5 water, 6 sand, 7 goop, 3 boundary, 0 rigid)")
        return Trajectory(position, particle_type)

    def __iter__(self) -> Iterator[Trajectory]:
        return (self[i] for i in range(len(self)))

    def close(self) -> None:
        self._h5.close()

    def __enter__(self) -> "Split":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # h5py handles cannot be pickled; DataLoader workers reopen the file.
    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.pop("_h5")
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._h5 = h5py.File(self.path, "r")


def open_split(folder: str | os.PathLike, split: str, min_frames: int = 1) -> Split:
    """Open one split of a dataset folder, checked against its metadata."""
    metadata = read_metadata(folder)
    return Split(split_path(folder, split), dim=metadata["dim"], min_frames=min_frames)


class Contents(NamedTuple):
    """What :func:`check_dataset` found: the metadata, and per split checked the ``[T, N, D]`` of
    each trajectory and the particle types it holds (``None`` for a split not read through)."""

    metadata: dict
    shapes: dict[str, list[tuple[int, int, int]]]
    particle_types: dict[str, list[int] | None]


def check_dataset(folder: str | os.PathLike, min_frames: int | dict[str, int] = 1,
                  splits: Iterable[str] = SPLITS, read: Iterable[str] | None = None) -> Contents:
    """Check a dataset before any work on it: ``metadata.json`` (keys, types, ranges), each of
    ``splits`` present, readable, of the right shapes and with at least ``min_frames`` frames per
    trajectory (one number, or one per split), and every trajectory of the splits in ``read``
    (default: all of ``splits``) read through: positions finite, particle types DeepMind's ids,
    particles that move (not all kinematic: a loss over none is NaN). Raises the first
    :class:`DatasetError`."""
    metadata = read_metadata(folder)
    splits = list(splits)
    read = splits if read is None else list(read)
    shapes, particle_types = {}, {}
    for split in splits:
        frames = min_frames.get(split, 1) if isinstance(min_frames, dict) else min_frames
        with Split(split_path(folder, split), dim=metadata["dim"], min_frames=frames) as data:
            shapes[split], particle_types[split] = data.shapes, None
            if split not in read:
                continue
            seen = set()
            for key, (position, particle_type) in zip(data.keys, data):
                check_bounds(position, metadata, data._where(key))
                if (particle_type == KINEMATIC).all():
                    raise DatasetError(f"{data._where(key)}: no moving particles (all {len(particle_type)} of "
                                       f"its particles are kinematic, type {KINEMATIC}): a loss over none is NaN")
                seen.update(np.unique(particle_type).tolist())
            particle_types[split] = sorted(seen)
    return Contents(metadata, shapes, particle_types)


def check_bounds(position: np.ndarray, metadata: dict, where: str) -> None:
    """Refuse positions ``[T, N, D]`` farther outside the metadata's ``bounds`` than one
    connectivity radius (particles sit on or just past a wall, never far beyond): data in other
    units or with wrong bounds would otherwise train or be scored as if nothing were wrong."""
    bounds = np.asarray(metadata["bounds"], dtype=np.float64)  # [D, 2]
    margin = float(metadata["default_connectivity_radius"])
    outside = (position < bounds[:, 0] - margin) | (position > bounds[:, 1] + margin)  # [T, N, D]
    if outside.any():
        frame, particle, axis = (int(i[0]) for i in np.nonzero(outside))
        raise DatasetError(f"{where}: 'position' leaves the metadata's 'bounds' {bounds.tolist()} by more than the "
                           f"connectivity radius ({margin}): first at frame {frame}, particle {particle}, axis "
                           f"{axis} ({float(position[frame, particle, axis]):.4g}); check the positions' units and "
                           "metadata 'bounds'")


# how far a checkpoint's data may differ from the data it is used on before it is named
STATS_TOLERANCE = 0.1  # of the checkpoint's std, for the velocity and acceleration means and stds
EXACT_TOLERANCE = 1e-6  # relative, for the radius, dt and bounds


def metadata_differences(trained: dict, data: dict) -> list[str]:
    """What differs between the metadata a model was trained with (``trained``) and the data's:
    ``dim``, ``stride`` (1 where absent: every frame), ``default_connectivity_radius``, ``dt`` and
    ``bounds`` beyond rounding (:data:`EXACT_TOLERANCE`), and the velocity and acceleration means
    and stds by more than :data:`STATS_TOLERANCE` of the trained std. One sentence per key, naming
    it; empty when they agree. A key missing on either side is not compared. A model trained on
    every k-th frame is compared with the data at that stride
    (:func:`rgns.data.datamodule.at_stride`), not with its ``metadata.json``."""
    differences = []
    if int(trained.get("stride") or 1) != int(data.get("stride") or 1):
        differences.append(f"'stride' {trained.get('stride') or 1} (trained) against {data.get('stride') or 1}")

    def present(key):
        return trained.get(key) is not None and data.get(key) is not None

    if present("dim") and int(trained["dim"]) != int(data["dim"]):
        differences.append(f"'dim' {trained['dim']} (trained) against {data['dim']}")
    for key in ("default_connectivity_radius", "dt"):
        if present(key):
            a, b = float(trained[key]), float(data[key])
            if abs(a - b) > EXACT_TOLERANCE * max(abs(a), abs(b)):
                differences.append(f"'{key}' {a:g} (trained) against {b:g}")
    if present("bounds"):
        a, b = np.asarray(trained["bounds"], dtype=float), np.asarray(data["bounds"], dtype=float)
        if a.shape != b.shape or np.abs(a - b).max() > EXACT_TOLERANCE * max(np.abs(a).max(), 1e-12):
            differences.append(f"'bounds' {a.tolist()} (trained) against {b.tolist()}")
    for kind in ("vel", "acc"):
        std = f"{kind}_std"
        if not present(std):
            continue
        scale = STATS_TOLERANCE * np.asarray(trained[std], dtype=float)
        for key in (f"{kind}_mean", std):
            if not present(key):
                continue
            a, b = np.asarray(trained[key], dtype=float), np.asarray(data[key], dtype=float)
            if a.shape != b.shape or (np.abs(a - b) > scale).any():
                differences.append(f"'{key}' {np.round(a, 8).tolist()} (trained) against {np.round(b, 8).tolist()} "
                                   f"(more than {STATS_TOLERANCE:g} of the trained '{std}' apart)")
    return differences


def validate_dataset(folder: str | os.PathLike, min_frames: int = 1) -> dict:
    """Read every trajectory of every split; raise the first contract violation. Returns metadata."""
    return check_dataset(folder, min_frames).metadata
