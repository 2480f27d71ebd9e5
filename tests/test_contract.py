"""The data contract: every broken input is refused with an error naming the file and what is wrong;
writes round-trip exactly and are atomic."""
from __future__ import annotations

import json
import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from rgns.data.contract import (
    REQUIRED_KEYS,
    SPLITS,
    DatasetError,
    open_split,
    read_metadata,
    validate_dataset,
    write_metadata,
    write_split,
)


def write_raw_split(path: Path, trajectories: dict[str, dict[str, np.ndarray]]) -> None:
    """Write an HDF5 split as given, bypassing write_split's checks, to make broken files."""
    with h5py.File(path, "w") as h5:
        for key, datasets in trajectories.items():
            group = h5.create_group(key)
            for name, data in datasets.items():
                group.create_dataset(name, data=data)


def good_trajectory(frames: int = 20, particles: int = 60, dim: int = 2) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(frames + particles + dim)
    return {
        "position": rng.uniform(0.1, 0.9, (frames, particles, dim)).astype(np.float32),
        "particle_type": np.full(particles, 5, dtype=np.int64),
    }


def with_broken_trajectory(folder: Path, **datasets: np.ndarray) -> Path:
    """Rewrite ``folder/train.h5`` as one good trajectory 00000 and a broken 00001; return its path."""
    path = folder / "train.h5"
    write_raw_split(path, {"00000": good_trajectory(), "00001": dict(good_trajectory(), **datasets)})
    return path


def raises_naming(*parts: str):
    """Expect a DatasetError whose message holds every part, literally and in order."""
    return pytest.raises(DatasetError, match=".*".join(re.escape(part) for part in parts))


def edit_metadata(folder: Path, **changes) -> Path:
    path = folder / "metadata.json"
    metadata = json.loads(path.read_text())
    metadata.update(changes)
    path.write_text(json.dumps(metadata))
    return path


# --- folders, files, metadata -------------------------------------------------------------------


def test_missing_folder(tmp_path):
    folder = tmp_path / "no_such_dataset"
    with raises_naming(str(folder), "dataset folder does not exist"):
        read_metadata(folder)
    with raises_naming(str(folder), "dataset folder does not exist"):
        open_split(folder, "train")


def test_missing_split(tiny_dataset):
    (tiny_dataset / "valid.h5").unlink()
    open_split(tiny_dataset, "train").close()
    with raises_naming(str(tiny_dataset / "valid.h5"), "split 'valid' is missing"):
        open_split(tiny_dataset, "valid")
    with raises_naming(str(tiny_dataset / "valid.h5"), "split 'valid' is missing"):
        validate_dataset(tiny_dataset)


def test_missing_metadata_file(tiny_dataset):
    (tiny_dataset / "metadata.json").unlink()
    with raises_naming(str(tiny_dataset / "metadata.json"), "metadata file is missing"):
        read_metadata(tiny_dataset)


@pytest.mark.parametrize("key", REQUIRED_KEYS)
def test_metadata_missing_key(tiny_dataset, key):
    path = tiny_dataset / "metadata.json"
    metadata = json.loads(path.read_text())
    del metadata[key]
    path.write_text(json.dumps(metadata))
    with raises_naming(str(path), f"missing key(s) {key}"):
        read_metadata(tiny_dataset)


@pytest.mark.parametrize("text", ['{"dim": 2,', "\xff\xfe not text", ""])
def test_metadata_not_json(tiny_dataset, text):
    path = tiny_dataset / "metadata.json"
    path.write_bytes(text.encode("latin-1"))
    with raises_naming(str(path), "not valid JSON"):
        read_metadata(tiny_dataset)


def test_metadata_not_an_object(tiny_dataset):
    path = tiny_dataset / "metadata.json"
    path.write_text("[1, 2, 3]")
    with raises_naming(str(path), "expected a JSON object, got list"):
        read_metadata(tiny_dataset)


def test_metadata_statistics_disagree_with_dim(tiny_dataset):
    path = edit_metadata(tiny_dataset, vel_std=[1e-3, 1e-3, 1e-3])
    with raises_naming(str(path), "'vel_std' has 3 entries, 'dim' is 2"):
        read_metadata(tiny_dataset)


def test_metadata_statistic_not_a_list(tiny_dataset):
    path = edit_metadata(tiny_dataset, acc_std=1e-4)
    with raises_naming(str(path), "'acc_std'", "a list of 2 numbers"):
        read_metadata(tiny_dataset)


# --- trajectories: shapes and dtypes, checked on open ---------------------------------------------


def test_dim_disagrees_with_positions(tiny_dataset):
    edit_metadata(
        tiny_dataset, dim=3, bounds=[[0.1, 0.9]] * 3, vel_mean=[0.0] * 3, vel_std=[1.0] * 3,
        acc_mean=[0.0] * 3, acc_std=[1.0] * 3,
    )
    with raises_naming(str(tiny_dataset / "train.h5"), "trajectory '00000'", "D=2 but metadata 'dim' is 3"):
        open_split(tiny_dataset, "train")


def test_positions_not_3d(tiny_dataset):
    path = with_broken_trajectory(tiny_dataset, position=np.zeros((20, 120), np.float32))
    with raises_naming(str(path), "trajectory '00001'", "'position' must be 3-D [T, N, D], got shape (20, 120)"):
        open_split(tiny_dataset, "train")


def test_positions_not_float(tiny_dataset):
    path = with_broken_trajectory(tiny_dataset, position=np.zeros((20, 60, 2), np.int32))
    with raises_naming(str(path), "trajectory '00001'", "'position' must be float, got int32"):
        open_split(tiny_dataset, "train")


def test_particle_type_length_not_n(tiny_dataset):
    path = with_broken_trajectory(tiny_dataset, particle_type=np.full(59, 5, np.int64))
    with raises_naming(str(path), "trajectory '00001'", "'particle_type' has shape (59,), expected (60,)"):
        open_split(tiny_dataset, "train")


def test_particle_type_not_integer(tiny_dataset):
    path = with_broken_trajectory(tiny_dataset, particle_type=np.full(60, 5.0))
    with raises_naming(str(path), "trajectory '00001'", "'particle_type' must be integer, got float64"):
        open_split(tiny_dataset, "train")


def test_trajectory_missing_a_dataset(tiny_dataset):
    path = tiny_dataset / "train.h5"
    write_raw_split(path, {"00000": {"position": good_trajectory()["position"]}})
    with raises_naming(str(path), "trajectory '00000'", "needs datasets 'position' and 'particle_type'"):
        open_split(tiny_dataset, "train")


def test_fewer_frames_than_a_window_needs(tiny_dataset):
    with open_split(tiny_dataset, "train", min_frames=20) as data:  # exactly enough is enough
        assert len(data) == 3
    path = tiny_dataset / "train.h5"
    with raises_naming(str(path), "trajectory '00000'", "20 frames, fewer than the 21 a window needs"):
        open_split(tiny_dataset, "train", min_frames=21)


# --- values: checked when a trajectory is read ----------------------------------------------------


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_positions(tiny_dataset, bad):
    position = good_trajectory()["position"]
    position[13, 7, 1] = bad
    path = with_broken_trajectory(tiny_dataset, position=position)
    with open_split(tiny_dataset, "train") as data:
        data[0]  # the good trajectory reads
        with raises_naming(str(path), "trajectory '00001'", "'position' holds NaN or Inf (first at frame 13)"):
            data[1]
    with raises_naming(str(path), "trajectory '00001'", "NaN or Inf"):
        validate_dataset(tiny_dataset)


# --- files that are not HDF5 ----------------------------------------------------------------------


def test_truncated_hdf5(tiny_dataset):
    path = tiny_dataset / "train.h5"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with raises_naming(str(path), "not a readable HDF5 file"):
        open_split(tiny_dataset, "train")


def test_not_hdf5(tiny_dataset):
    path = tiny_dataset / "test.h5"
    path.write_text("position,particle_type\n0.5,5\n")
    with raises_naming(str(path), "not a readable HDF5 file"):
        open_split(tiny_dataset, "test")


# --- writing --------------------------------------------------------------------------------------


def test_round_trip(tmp_path, tiny_dataset):
    rng = np.random.default_rng(3)
    trajectories = [
        (rng.uniform(size=(7, n, 3)).astype(np.float32), rng.integers(0, 9, n).astype(np.int64)) for n in (5, 1, 9)
    ]
    trajectories[0][0][2, 1, 0] = -0.0
    metadata = dict(json.loads((tiny_dataset / "metadata.json").read_text()), dim=3, bounds=[[0.0, 1.0]] * 3)
    for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        metadata[key] = (rng.normal(size=3) if key.endswith("mean") else rng.uniform(0.5, 2.0, 3)).tolist()
    metadata["generator"] = {"name": "test", "seed": 3}
    folder = tmp_path / "roundtrip"
    for split in SPLITS:
        assert write_split(folder / f"{split}.h5", iter(trajectories)) == 3
    write_metadata(folder, metadata)

    assert validate_dataset(folder, min_frames=7) == metadata
    with open_split(folder, "valid") as data:
        assert data.keys == ["00000", "00001", "00002"]
        assert data.shapes == [(7, 5, 3), (7, 1, 3), (7, 9, 3)]
        for (position, particle_type), got in zip(trajectories, data):
            assert got.position.dtype == np.float32 and got.particle_type.dtype == np.int64
            assert np.array_equal(got.position.view(np.uint32), position.view(np.uint32))
            assert np.array_equal(got.particle_type, particle_type)


def test_split_survives_pickling(tiny_dataset):
    """DataLoader workers get a pickled Split and must reopen the file."""
    import pickle

    with open_split(tiny_dataset, "train") as data:
        copy = pickle.loads(pickle.dumps(data))
        try:
            assert np.array_equal(copy[2].position, data[2].position)
        finally:
            copy.close()


def test_write_metadata_refuses_incomplete(tmp_path):
    with raises_naming(str(tmp_path), "metadata to write lacks key(s) dt"):
        write_metadata(tmp_path, {key: 0 for key in REQUIRED_KEYS if key != "dt"})
    assert list(tmp_path.iterdir()) == []


def trajectories_then(failure: Exception, good: int = 1):
    """Yield ``good`` trajectories, then raise ``failure`` mid-stream."""
    rng = np.random.default_rng(7)
    for _ in range(good):
        yield rng.normal(size=(4, 3, 2)).astype(np.float32), np.full(3, 5, np.int64)
    raise failure


def test_interrupted_write_keeps_the_previous_file(tiny_dataset):
    path = tiny_dataset / "train.h5"
    before, listing = path.read_bytes(), sorted(p.name for p in tiny_dataset.iterdir())
    with pytest.raises(RuntimeError, match="simulator crashed"):
        write_split(path, trajectories_then(RuntimeError("simulator crashed")))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tiny_dataset.iterdir()) == listing  # no temporary file left behind
    with open_split(tiny_dataset, "train") as data:
        assert len(data) == 3


def test_interrupted_first_write_leaves_nothing(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        write_split(tmp_path / "train.h5", trajectories_then(KeyboardInterrupt(), good=2))
    assert list(tmp_path.iterdir()) == []


def test_write_refuses_a_malformed_trajectory(tiny_dataset):
    path = tiny_dataset / "test.h5"
    before = path.read_bytes()
    good = (np.zeros((4, 3, 2), np.float32), np.full(3, 5, np.int64))
    bad = (np.zeros((4, 3, 2), np.float32), np.full(2, 5, np.int64))
    with raises_naming(str(path), "trajectory 00001", "particle_type (2,)"):
        write_split(path, [good, bad])
    assert path.read_bytes() == before
    assert not [p for p in tiny_dataset.iterdir() if p.name.endswith(".tmp")]
