"""Scene generation: reproducible bytes, resumable, metadata as the data contract wants."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

import rgns.data.generate as generate
import rgns.data.subset as subset
from rgns.data.contract import KINEMATIC, SPLITS, WATER, DatasetError, open_split, read_metadata, validate_dataset
from rgns.data.generate import generate_dataset, scene_config
from rgns.data.stats import compute_statistics

TINY = dict(num_trajectories=2, num_frames=12, seed=3, workers=1, progress=False)


def tiny_scene(name="waterdrop"):
    cfg = scene_config(name)
    cfg["splits"] = {"train": 2, "valid": 1, "test": 1}
    return cfg


def split_bytes(folder):
    return {name: (folder / name).read_bytes() for name in ("train.h5", "valid.h5", "test.h5", "metadata.json")}


@pytest.fixture(scope="module")
def waterdrop(tmp_path_factory):
    return generate_dataset(tiny_scene(), tmp_path_factory.mktemp("data") / "waterdrop", **TINY)


def test_dataset_follows_the_contract(waterdrop):
    metadata = validate_dataset(waterdrop)
    assert metadata["sequence_length"] == 11 and metadata["dim"] == 2 and metadata["dt"] == 0.0025
    assert metadata["bounds"] == [[0.1, 0.5], [0.1, 0.5]] and metadata["gravity"] == [0.0, -9.81]
    assert metadata["generator"]["scene"] == "waterdrop" and metadata["generator"]["seed"] == 3
    assert metadata["generator"]["params"]["spacing"] == 0.0065 and "version" in metadata["generator"]
    with open_split(waterdrop, "train") as train:
        assert len(train) == 2
        assert metadata["num_particles_max"] >= max(shape[1] for shape in train.shapes)
        expected = compute_statistics(train)
        for position, particle_type in train:
            assert position.shape[0] == 12 and (particle_type == WATER).all()
    for key, value in expected.items():
        np.testing.assert_allclose(metadata[key], value)
    assert not (waterdrop / ".parts").exists()


def test_spacing_gives_10_to_25_neighbours(waterdrop):
    metadata = read_metadata(waterdrop)
    with open_split(waterdrop, "train") as train:
        for position, _ in train:
            pairs = cKDTree(position[0]).query_pairs(metadata["default_connectivity_radius"])
            assert 10 <= 2 * len(pairs) / position.shape[1] <= 25


def test_same_seed_same_bytes_other_seed_other_data(waterdrop, tmp_path):
    again = generate_dataset(tiny_scene(), tmp_path / "again", **TINY)
    assert split_bytes(again) == split_bytes(waterdrop)
    other = generate_dataset(tiny_scene(), tmp_path / "other", **{**TINY, "seed": 4})
    assert (other / "train.h5").read_bytes() != (waterdrop / "train.h5").read_bytes()


def test_interrupted_generation_resumes_without_redoing_work(waterdrop, tmp_path, monkeypatch):
    simulate, calls = generate._simulate, []

    def interrupted(task):
        if len(calls) == 3:
            raise KeyboardInterrupt
        calls.append(task[1:3])
        return simulate(task)

    monkeypatch.setattr(generate, "_simulate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        generate_dataset(tiny_scene(), tmp_path / "resumed", **TINY)
    assert (tmp_path / "resumed" / "train.h5").exists() is False  # no split before all its parts
    assert not (tmp_path / "resumed" / "metadata.json").exists()
    calls.clear()
    monkeypatch.setattr(generate, "_simulate", lambda task: (calls.append(task[1:3]), simulate(task))[1])
    resumed = generate_dataset(tiny_scene(), tmp_path / "resumed", **TINY)
    assert calls == [("test", 0)]  # only the missing trajectory
    assert split_bytes(resumed) == split_bytes(waterdrop)


def test_other_settings_never_mix_into_a_folder(waterdrop):
    with pytest.raises(DatasetError, match="other settings"):
        generate_dataset(tiny_scene(), waterdrop, **{**TINY, "seed": 5})
    assert generate_dataset(tiny_scene(), waterdrop, **TINY) == waterdrop  # complete: nothing to do


def test_ramps_are_static_kinematic_particles(tmp_path):
    cfg = tiny_scene("waterramps")
    folder = generate_dataset(cfg, tmp_path / "ramps", **TINY)
    with open_split(folder, "train") as train:
        for position, particle_type in train:
            static = particle_type == KINEMATIC
            assert static.any() and (particle_type[~static] == WATER).all()
            assert (position[:, static] == position[:1, static]).all()
            assert position.min() >= np.float32(0.1) and position.max() <= np.float32(0.5)  # the 0.4 m box


@pytest.mark.parametrize("name", ["sand", "dambreak", "dambreak_sph"])
def test_other_scenes_generate(name, tmp_path):
    folder = generate_dataset(tiny_scene(name), tmp_path / name, **{**TINY, "num_frames": 5})
    metadata = validate_dataset(folder)
    assert metadata["generator"]["scene"] == name and metadata["sequence_length"] == 4


def test_water3d_writes_a_valid_3d_dataset(tmp_path):
    """SPH in 3D: positions [T, N, 3] in the box, finite, ~18 neighbours within R at rest."""
    folder = generate_dataset(tiny_scene("water3d"), tmp_path / "water3d", **{**TINY, "num_frames": 20})
    metadata = validate_dataset(folder)
    assert metadata["dim"] == 3 and metadata["sequence_length"] == 19 and metadata["bounds"] == [[0.1, 0.5]] * 3
    lower, upper = np.float32(0.1), np.float32(0.5)
    for split in SPLITS:
        with open_split(folder, split) as data:
            for position, particle_type in data:
                assert position.shape == (20, len(particle_type), 3) and (particle_type == WATER).all()
                assert np.isfinite(position).all() and position.min() >= lower and position.max() <= upper
                assert (np.abs(np.diff(position, axis=0)) > 0).any(-1).mean() > 0.9  # it moves
                pairs = cKDTree(position[0]).query_pairs(metadata["default_connectivity_radius"])
                assert 10 <= 2 * len(pairs) / position.shape[1] <= 25


def test_water3d_full_preset_is_water3d_scale():
    cfg = scene_config("water3d_full")
    assert cfg["dim"] == 3 and cfg["num_frames"] == 801 and cfg["particles"][1] >= 13000
    assert cfg["capacity"] >= cfg["particles"][1] and cfg["connectivity_radius"] == 0.035
    assert cfg["solver"]["_target_"] == "rgns.physics.sph.SPHSolver"
    from hydra.utils import instantiate

    scene = instantiate(cfg)  # draws layouts only; no solver is made
    for seed in range(3):
        position = scene.sample(np.random.default_rng(seed))["position"]
        assert 4000 <= len(position) <= 13500 and position.shape[1] == 3


def test_cli_composes_overrides_and_leaves_cwd_clean(tmp_path):
    out = tmp_path / "cli"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-m", "rgns.data.generate", "scene=waterdrop", f"out_dir={out}",
                    "num_trajectories=1", "num_frames=4", "seed=7", "workers=1",
                    "scene.splits.valid=1", "scene.splits.test=1"], cwd=tmp_path, env=env, check=True,
                   capture_output=True)
    metadata = json.loads((out / "metadata.json").read_text())
    assert metadata["sequence_length"] == 3 and metadata["generator"]["seed"] == 7
    assert metadata["generator"]["num_trajectories"] == {"train": 1, "valid": 1, "test": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cli"]  # no outputs/ folder


@pytest.mark.slow
def test_two_workers_give_the_same_bytes_as_one(waterdrop, tmp_path):
    parallel = generate_dataset(tiny_scene(), tmp_path / "parallel", **{**TINY, "workers": 2})
    assert split_bytes(parallel) == split_bytes(waterdrop)


@pytest.mark.slow
def test_waterdrop_preset_statistics_are_deepminds(tmp_path):
    """Per-frame velocity and acceleration std within a factor 2 of DeepMind's WaterDrop."""
    cfg = scene_config("waterdrop_full")
    cfg["splits"] = {"train": 6, "valid": 1, "test": 1}
    folder = generate_dataset(cfg, tmp_path / "full", seed=0, workers=2, progress=False)
    metadata = read_metadata(folder)
    deepmind = {"vel_std": [1.37e-3, 1.31e-3], "acc_std": [6.74e-5, 8.70e-5]}
    for key, reference in deepmind.items():
        ratio = np.asarray(metadata[key]) / reference
        assert ((ratio > 0.5) & (ratio < 2.0)).all(), (key, metadata[key])
    assert metadata["sequence_length"] == 1000 and metadata["num_particles_max"] <= 1100


def test_split_sizes_are_settable_and_a_larger_split_extends_a_smaller_one(waterdrop, tmp_path):
    """Trajectory i of a split is seeded by (seed, split, i): more validation trajectories keep the
    ones a smaller split had, so results on the smaller one stay comparable."""
    larger = generate_dataset(tiny_scene(), tmp_path / "larger", splits={"valid": 2, "test": None}, **TINY)
    with open_split(larger, "valid") as valid, open_split(waterdrop, "valid") as small:
        assert len(valid) == 2 and len(small) == 1
        np.testing.assert_array_equal(valid[0].position, small[0].position)
        first, second = valid[0].position, valid[1].position
        assert first.shape != second.shape or not np.array_equal(first, second)  # a trajectory of its own
    assert read_metadata(larger)["generator"]["num_trajectories"] == {"train": 2, "valid": 2, "test": 1}
    with pytest.raises(ValueError, match="unknown split"):
        generate_dataset(tiny_scene(), tmp_path / "bad", splits={"validation": 2}, **TINY)
    assert not (tmp_path / "bad").exists()


def test_subset_keeps_the_chosen_trajectories_and_recomputes_what_depends_on_them(waterdrop, tmp_path):
    target = subset.main([str(waterdrop), str(tmp_path / "second"), "--split", "train", "--trajectories", "1"])
    metadata = validate_dataset(target)
    source = read_metadata(waterdrop)
    with open_split(waterdrop, "train") as full, open_split(target, "train") as part:
        assert len(part) == 1 and (part[0].position == full[1].position).all()
        assert {k: metadata[k] for k in ("vel_std", "acc_std")} != {k: source[k] for k in ("vel_std", "acc_std")}
        assert {k: metadata[k] for k in ("vel_mean", "vel_std", "acc_mean", "acc_std")} == compute_statistics(part)
        others = [t for name in ("valid", "test") for t in open_split(waterdrop, name)]
        assert metadata["num_particles_max"] == max(t.position.shape[1] for t in [part[0], *others])
    for name in ("valid.h5", "test.h5"):  # the other splits as they are
        assert (target / name).read_bytes() == (waterdrop / name).read_bytes()
    assert metadata["subset"] == {"source": str(waterdrop), "split": "train", "trajectories": [1]}
    assert metadata["generator"]["draws"] == {"train": [1]}
    # a subset of the subset records the first draw numbers
    again = subset.make_subset(target, tmp_path / "again", "train", [0])
    assert read_metadata(again)["generator"]["draws"] == {"train": [1]}


def test_subset_refuses_bad_choices_and_never_touches_an_existing_folder(waterdrop, tmp_path):
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    with pytest.raises(DatasetError, match="existing: already exists"):
        subset.make_subset(waterdrop, existing, "train", "0")
    assert [p.name for p in existing.iterdir()] == ["keep.txt"]
    for text, match in [("0:3", r"'0:3' is neither .* STOP <= 2"), ("0,0", r"trajectories \[0\] more than once"),
                        ("x", "'x' is neither"), ("1:1", "'1:1' is neither"), ("-1", "'-1' is neither")]:
        with pytest.raises(ValueError, match=match):
            subset.make_subset(waterdrop, tmp_path / "new", "train", text)
    with pytest.raises(ValueError, match="unknown split 'tests'"):
        subset.make_subset(waterdrop, tmp_path / "new", "tests", "0")
    with pytest.raises(DatasetError, match=r"test.h5: has 1 trajectories; no trajectory \[1\]"):
        subset.make_subset(waterdrop, tmp_path / "new", "test", [1])
    with pytest.raises(ValueError, match=r"trajectories \[0, 1, 0\]: index \[0\] more than once"):
        subset.make_subset(waterdrop, tmp_path / "new", "train", [0, 1, 0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing"]  # nothing half written left behind
