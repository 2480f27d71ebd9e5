"""DeepMind TFRecord -> rgns conversion: exact values, streaming memory, clear errors, atomic output."""
from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from tfrecord import example_pb2
from tfrecord.reader import tfrecord_iterator
from tfrecord.writer import TFRecordWriter

from rgns.data.contract import KINEMATIC, RIGID, SPLITS, WATER, DatasetError, open_split, validate_dataset
from rgns.data.convert import convert, main


def deepmind_metadata(dim: int = 2, sequence_length: int = 9) -> dict:
    return {
        "bounds": [[0.1, 0.9]] * dim,
        "sequence_length": sequence_length,
        "default_connectivity_radius": 0.015,
        "dim": dim,
        "dt": 0.0025,
        "vel_mean": [-3.96e-5] * dim,
        "vel_std": [1.37e-3] * dim,
        "acc_mean": [2.6e-8] * dim,
        "acc_std": [6.74e-5] * dim,
    }


def deepmind_trajectory(rng: np.random.Generator, frames: int, particles: int, dim: int):
    """Random float32 positions with awkward values (zeros, -0, a denormal) and types ending in 0.

    Trailing zero bytes in both features catch any decoding that strips NULs from bytes.
    """
    position = rng.uniform(0.1, 0.9, (frames, particles, dim)).astype(np.float32)
    position[-1, -1] = 0.0
    position[0, 0, 0] = -0.0
    position[1, 0, 0] = np.float32(1e-40)
    particle_type = rng.choice([WATER, KINEMATIC], particles).astype(np.int64)
    particle_type[-1] = RIGID
    return position, particle_type


def write_deepmind_tfrecord(path: Path, records: list[dict]) -> None:
    """Write records in DeepMind's format: a SequenceExample per trajectory, with context ``key``
    (int64) and ``particle_type`` (one bytes value) and sequence ``position`` (one bytes value per
    frame). A record may leave a feature out, or give raw bytes per frame, to make a bad record."""
    writer = TFRecordWriter(str(path))
    for record in records:
        context = {}
        if "key" in record:
            context["key"] = (record["key"], "int")
        if "particle_type" in record:
            context["particle_type"] = (np.asarray(record["particle_type"], "<i8").tobytes(), "byte")
        sequence = {}
        if "position" in record:
            frames = [f if isinstance(f, bytes) else np.asarray(f, "<f4").tobytes() for f in record["position"]]
            sequence["position"] = (frames, "byte")
        else:
            sequence["velocity"] = ([b"\x00" * 8], "byte")  # some sequence feature, but not 'position'
        writer.write(context, sequence)
    writer.close()


def make_source(folder: Path, trajectories: dict[str, list], metadata: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "metadata.json").write_text(json.dumps(metadata))
    for split, trajs in trajectories.items():
        records = [{"key": key, "position": p, "particle_type": t} for key, (p, t) in enumerate(trajs)]
        write_deepmind_tfrecord(folder / f"{split}.tfrecord", records)
    return folder


@pytest.fixture
def source(tmp_path):
    """A 2D DeepMind-format folder: 3 train, 2 valid, 2 test trajectories of 10 frames,
    particle counts differing between trajectories."""
    rng = np.random.default_rng(0)
    metadata = deepmind_metadata()
    trajectories = {
        split: [deepmind_trajectory(rng, 10, particles, 2) for particles in counts]
        for split, counts in zip(SPLITS, ([7, 12, 5], [9, 4], [6, 11]))
    }
    return make_source(tmp_path / "deepmind", trajectories, metadata), trajectories, metadata


def folder_state(folder: Path) -> dict[str, bytes]:
    """Every file under a folder (hidden ones included) and its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_fixture_writes_deepmind_record_layout(source):
    src, trajectories, _ = source
    raw = next(iter(tfrecord_iterator(str(src / "train.tfrecord"))))
    example = example_pb2.SequenceExample()
    example.ParseFromString(bytes(raw))
    position, particle_type = trajectories["train"][0]
    assert list(example.context.feature["key"].int64_list.value) == [0]
    assert list(example.context.feature["particle_type"].bytes_list.value) == [particle_type.tobytes()]
    steps = example.feature_lists.feature_list["position"].feature
    assert len(steps) == len(position)
    assert [list(step.bytes_list.value) for step in steps] == [[frame.tobytes()] for frame in position]


@pytest.mark.parametrize("dim", [2, 3])
def test_convert_is_bit_exact(tmp_path, dim):
    rng = np.random.default_rng(dim)
    metadata = deepmind_metadata(dim, sequence_length=7)
    metadata["context_mean"] = [0.5]  # a key of DeepMind's we do not use must still be carried over
    metadata["bounds"] = [[0.0, 1.0]] * dim  # the awkward values (0, -0, a denormal) on the wall, not past it
    trajectories = {split: [deepmind_trajectory(rng, 8, n, dim) for n in (13, 3)] for split in SPLITS}
    src = make_source(tmp_path / "src", trajectories, metadata)

    out = convert(src, tmp_path / "dst", progress=False)

    assert validate_dataset(tmp_path / "dst", min_frames=8) == out
    for split in SPLITS:
        with open_split(tmp_path / "dst", split) as data:
            assert len(data) == len(trajectories[split])
            for (position, particle_type), got in zip(trajectories[split], data):
                assert got.position.dtype == np.float32 and got.particle_type.dtype == np.int64
                assert np.array_equal(got.position.view(np.uint32), position.view(np.uint32))  # -0.0 too
                assert np.array_equal(got.particle_type, particle_type)
    assert {key: out[key] for key in metadata} == metadata
    assert out["num_particles_max"] == 13
    assert out["generator"] == "rgns.data.convert"
    assert out["source"]["path"] == str(src.resolve())
    assert out["source"]["trajectories"] == {split: 2 for split in SPLITS}


def test_cli(source, tmp_path, capsys):
    src, trajectories, _ = source
    main([str(src), str(tmp_path / "dst"), "--splits", "valid"])
    assert sorted(p.name for p in (tmp_path / "dst").iterdir()) == ["metadata.json", "valid.h5"]
    with open_split(tmp_path / "dst", "valid") as data:
        assert np.array_equal(data[1].position, trajectories["valid"][1][0])
    with pytest.raises(SystemExit) as exit_info:
        main([str(tmp_path / "nowhere"), str(tmp_path / "dst2")])
    assert exit_info.value.code == 1
    assert "nowhere: source folder does not exist" in capsys.readouterr().err


def test_refuses_to_overwrite_without_flag(source, tmp_path):
    src, _, _ = source
    convert(src, tmp_path / "dst", progress=False)
    before = folder_state(tmp_path / "dst")
    with pytest.raises(DatasetError, match=r"already holds metadata\.json, train\.h5.*--overwrite"):
        convert(src, tmp_path / "dst", progress=False)
    assert folder_state(tmp_path / "dst") == before
    convert(src, tmp_path / "dst", overwrite=True, progress=False)


@pytest.mark.parametrize(
    "damage, message",
    [
        ("no_folder", r"deepmind: source folder does not exist"),
        ("no_metadata", r"deepmind/metadata\.json: metadata file is missing"),
        ("no_split", r"deepmind/test\.tfrecord: split 'test' is missing"),
        ("truncated", r"deepmind/valid\.tfrecord, record 1: truncated file"),
    ],
)
def test_bad_source_is_named_and_nothing_is_written(source, tmp_path, damage, message):
    src, _, _ = source
    if damage == "no_folder":
        src = tmp_path / "deepmind"
        for path in src.iterdir():
            path.unlink()
        src.rmdir()
    elif damage == "no_metadata":
        (src / "metadata.json").unlink()
    elif damage == "no_split":
        (src / "test.tfrecord").unlink()
    elif damage == "truncated":
        path = src / "valid.tfrecord"
        path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(DatasetError, match=message):
        convert(src, tmp_path / "dst", progress=False)
    assert not (tmp_path / "dst").exists()


def bad_records(rng: np.random.Generator) -> dict[str, tuple[dict, str]]:
    good_position, good_type = deepmind_trajectory(rng, 10, 5, 2)
    nan_position = good_position.copy()
    nan_position[4, 2, 1] = np.nan
    inf_position = good_position.copy()
    inf_position[6, 0, 0] = -np.inf
    return {
        "no_position": ({"key": 1, "particle_type": good_type}, r"sequence feature 'position' is missing"),
        "no_particle_type": ({"key": 1, "position": good_position}, r"context feature 'particle_type' is missing"),
        "frames_disagree": (  # 12 frames where metadata says sequence_length + 1 = 10
            {"key": 1, "position": np.concatenate([good_position, good_position[:2]]), "particle_type": good_type},
            r"'position' holds 120 float32 values, which do not reshape to \[T=10, N=5, dim=2\]",
        ),
        "particles_disagree": (
            {"key": 1, "position": good_position, "particle_type": good_type[:4]},
            r"'position' holds 100 float32 values, which do not reshape to \[T=10, N=4, dim=2\]",
        ),
        "ragged_bytes": (
            {"key": 1, "position": [frame.tobytes()[:-1] for frame in good_position], "particle_type": good_type},
            r"'position' has 390 bytes, not a whole number of float32",
        ),
        "nan": (
            {"key": 1, "position": nan_position, "particle_type": good_type},
            r"'position' holds NaN or Inf \(first at frame 4\)",
        ),
        "inf": (
            {"key": 1, "position": inf_position, "particle_type": good_type},
            r"'position' holds NaN or Inf \(first at frame 6\)",
        ),
        "unknown_type": (
            {"key": 1, "position": good_position, "particle_type": np.full(5, 12)},
            r"'particle_type' holds ids outside \[0, 9\): \[12\]",
        ),
    }


@pytest.mark.parametrize("case", list(bad_records(np.random.default_rng(0))))
def test_bad_record_is_named_and_previous_dataset_survives(source, tmp_path, case):
    src, _, metadata = source
    convert(src, tmp_path / "dst", progress=False)
    before = folder_state(tmp_path / "dst")

    rng = np.random.default_rng(1)
    # new train data, so that a conversion that wrote train.h5 before failing on valid would show
    make_source(src, {"train": [deepmind_trajectory(rng, 10, 8, 2)]}, metadata)
    record, message = bad_records(rng)[case]
    good_position, good_type = deepmind_trajectory(rng, 10, 5, 2)
    good = {"key": 0, "position": good_position, "particle_type": good_type}
    write_deepmind_tfrecord(src / "valid.tfrecord", [good, record])

    with pytest.raises(DatasetError, match=r"deepmind/valid\.tfrecord, record 1: " + message):
        convert(src, tmp_path / "dst", overwrite=True, progress=False)
    assert folder_state(tmp_path / "dst") == before  # no new file, no staging folder, old files intact


def converted_peak(src: Path, dst: Path) -> int:
    """Peak of Python-traced memory (numpy buffers and bytes included) during one conversion."""
    tracemalloc.start()
    try:
        convert(src, dst, splits=["train"], overwrite=True, progress=False)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_memory_does_not_grow_with_file_length(tmp_path):
    """Four times the records of the same size: the peak must stay within 1.5x, not grow 4x."""
    rng = np.random.default_rng(0)
    frames, particles, dim = 100, 500, 2
    record_bytes = frames * particles * dim * 4  # 400 kB of positions per record
    metadata = deepmind_metadata(dim, sequence_length=frames - 1)
    trajectory = deepmind_trajectory(rng, frames, particles, dim)
    short = make_source(tmp_path / "short", {"train": [trajectory] * 4}, metadata)
    long = make_source(tmp_path / "long", {"train": [trajectory] * 16}, metadata)

    convert(short, tmp_path / "warmup", splits=["train"], progress=False)  # lazy imports, caches
    short_peak = converted_peak(short, tmp_path / "dst_short")
    long_peak = converted_peak(long, tmp_path / "dst_long")

    assert short_peak > record_bytes  # the trace does see the data, so the comparison means something
    assert long_peak < 1.5 * short_peak, (short_peak, long_peak)
    with open_split(tmp_path / "dst_long", "train") as data:
        assert len(data) == 16 and np.array_equal(data[15].position, trajectory[0])
