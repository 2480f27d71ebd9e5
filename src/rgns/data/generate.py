"""Generate a scene's dataset: ``python -m rgns.data.generate scene=NAME out_dir=DIR``.

Command line (Hydra overrides of ``generate.yaml`` in :func:`rgns.config_dir`, the repo's ``conf/``;
nothing is written to the cwd)::

    python -m rgns.data.generate scene=waterdrop out_dir=data/waterdrop \
        [num_trajectories=N] [num_frames=T] [seed=S] [workers=2] [arch=cpu] [scene.splits.valid=4 ...]

Python::

    from rgns.data.generate import generate_dataset
    generate_dataset("waterdrop", "data/waterdrop", num_trajectories=None, num_frames=None,
                     seed=0, workers=2, arch="cpu", progress=True) -> Path

``scene`` is a config name under ``conf/scene/`` (``waterdrop``, ``waterdrop_full``,
``waterramps``, ``sand``, ``water3d``, ``dambreak``, each ``*_full`` at the original scale) or a
scene config mapping. ``num_trajectories`` sets the train split's size (valid and test keep the
scene's ``splits``); ``num_frames`` the frames per trajectory (``sequence_length + 1``); ``None``
keeps the scene's values.

What it guarantees:

- the same (scene, sizes, seed) gives the same bytes, whatever ``workers``: trajectory ``i`` of a
  split draws from ``numpy.random.default_rng([seed, split_index, i])`` and Taichi runs on one
  thread per process (CPU);
- ``workers`` processes (spawned) simulate trajectories in parallel, a progress bar counts them;
- each finished trajectory is saved in ``out_dir/.parts/``; a restart skips them, and a split
  file appears (atomically) only once all its trajectories exist; ``metadata.json`` is written
  last, so a folder with ``metadata.json`` is complete. A folder made with other settings, or
  holding split files without a ``metadata.json`` or plan of this generation, or an unreadable
  ``metadata.json``, is never mixed with: generation stops with an error naming it;
- ``metadata.json`` carries DeepMind's keys (statistics from the train split) plus
  ``num_particles_max``, ``gravity``, ``regime`` (:func:`rgns.data.stats.regime_summary` of the
  train split: mean neighbours over each trajectory, kinetic energy left at the end) and
  ``generator`` = {scene, params, seed, version, ...}.
"""
from __future__ import annotations

import json
import multiprocessing
import shutil
import sys
from importlib.metadata import PackageNotFoundError, version as package_version
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from rgns import config_dir as package_config_dir
from rgns.data.contract import SPLITS, DatasetError, Split, atomic_path, write_metadata, write_split
from rgns.data.stats import compute_statistics, regime_summary

GENERATOR_VERSION = 1  # bump when the same config and seed would give other data


def compose(overrides: Sequence[str] = (), config_dir: str | Path | None = None):
    """Compose ``generate.yaml`` from ``config_dir`` (default: the package's, :func:`rgns.config_dir`)
    with Hydra overrides (no run directory, no logging setup).

    Works inside a running Hydra app too (``train.py`` generating its dataset on first use): the
    app's global Hydra state is set aside for the composition and put back afterwards."""
    from hydra import compose as hydra_compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    global_hydra = GlobalHydra.instance()
    outer = global_hydra.hydra if global_hydra.is_initialized() else None
    global_hydra.clear()
    try:
        config_dir = Path(config_dir or package_config_dir()).resolve()
        with initialize_config_dir(config_dir=str(config_dir), version_base=None):
            cfg = hydra_compose("generate", overrides=list(overrides))
    finally:
        if outer is not None:
            global_hydra.clear()
            global_hydra.initialize(outer)
    OmegaConf.resolve(cfg)
    return cfg


def scene_config(scene: str | Mapping, config_dir: str | Path | None = None) -> dict:
    """A scene's config as a plain dict, from its name under ``conf/scene/`` or a mapping."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(scene, str):
        return OmegaConf.to_container(compose([f"scene={scene}", "out_dir=unused"], config_dir).scene)
    if isinstance(scene, DictConfig):
        return OmegaConf.to_container(scene, resolve=True)
    return json.loads(json.dumps(dict(scene)))  # a deep, plain copy


def _version() -> str:
    try:
        return f"rgns {package_version('rgns')}, generator {GENERATOR_VERSION}"
    except PackageNotFoundError:
        return f"generator {GENERATOR_VERSION}"


# ---------------------------------------------------------------- one trajectory, in a worker
_scenes: dict[str, object] = {}


def _simulate(task: tuple) -> tuple[str, int]:
    """Simulate one trajectory and save it as a part file; runs in a worker process."""
    cfg, split, index, seed, num_frames, parts, arch = task
    from hydra.utils import instantiate

    from rgns.physics.runtime import init_taichi

    init_taichi(arch=arch, num_threads=1)
    key = json.dumps(cfg, sort_keys=True)
    if key not in _scenes:
        _scenes[key] = instantiate(cfg)
    rng = np.random.default_rng([seed, SPLITS.index(split), index])
    position, particle_type = _scenes[key].trajectory(rng, num_frames)
    with atomic_path(_part_path(Path(parts), split, index)) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, position=position, particle_type=particle_type)
    return split, index


def _part_path(parts: Path, split: str, index: int) -> Path:
    return parts / f"{split}-{index:05d}.npz"


def _load_part(parts: Path, split: str, index: int) -> tuple[np.ndarray, np.ndarray]:
    with np.load(_part_path(parts, split, index)) as part:
        return part["position"], part["particle_type"]


# ---------------------------------------------------------------- the dataset
def _read_json(path: Path, what: str):
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DatasetError(f"{path}: not valid JSON ({err}), so not {what}; the folder's files cannot be trusted: "
                           "choose another out_dir or delete them") from None


def generate_dataset(scene: str | Mapping, out_dir: str | Path, num_trajectories: int | None = None,
                     num_frames: int | None = None, seed: int = 0, workers: int = 2, arch: str = "cpu",
                     progress: bool = True, splits: Mapping[str, int | None] | None = None) -> Path:
    """Generate (or finish generating) a dataset folder; returns its path. See the module docs.

    ``splits`` sets the trajectories of some splits (e.g. ``{"valid": 8, "test": 8}``; ``None``
    keeps the scene's count); ``num_trajectories`` is the train split's, as before."""
    cfg = scene_config(scene)
    unknown = set(splits or {}) - set(SPLITS)
    if unknown:
        raise ValueError(f"splits: unknown split(s) {sorted(unknown)}; the splits are {list(SPLITS)}")
    counts = {split: int(cfg["splits"][split]) for split in SPLITS}
    counts.update({split: int(n) for split, n in (splits or {}).items() if n is not None})
    if num_trajectories is not None:
        counts["train"] = int(num_trajectories)
    if any(n < 1 for n in counts.values()):
        raise ValueError(f"every split needs at least one trajectory, got {counts}")
    num_frames = int(num_frames or cfg["num_frames"])
    if num_frames < 3:
        raise ValueError(f"num_frames={num_frames}: need at least 3 (an acceleration)")
    generator = {"scene": cfg["name"], "params": cfg, "seed": int(seed), "version": _version(),
                 "num_trajectories": counts, "num_frames": num_frames}

    out_dir = Path(out_dir)
    parts = out_dir / ".parts"
    metadata_path = out_dir / "metadata.json"
    if metadata_path.is_file():
        made_with = _read_json(metadata_path, "the metadata of a finished dataset")
        made_with = made_with.get("generator") if isinstance(made_with, dict) else made_with
        if made_with != json.loads(json.dumps(generator)):
            raise DatasetError(f"{out_dir}: holds a dataset made with other settings ({made_with}); "
                               "choose another out_dir or delete it")
        return out_dir
    plan_path = parts / "plan.json"
    if plan_path.is_file():
        if _read_json(plan_path, "the plan of an unfinished generation") != json.loads(json.dumps(generator)):
            raise DatasetError(f"{out_dir}: an unfinished generation with other settings is in {parts}; "
                               "delete it or rerun with its settings")
    else:
        strays = [f"{split}.h5" for split in SPLITS if (out_dir / f"{split}.h5").exists()]
        if strays:  # split files without a plan: not this generation's, and they would be kept
            raise DatasetError(f"{out_dir}: holds {', '.join(strays)} but no metadata.json and no unfinished "
                               f"generation ({plan_path}): files from something else; choose another out_dir "
                               "or delete them")
        with atomic_path(plan_path) as tmp:
            tmp.write_text(json.dumps(generator, indent=2, sort_keys=True))

    todo = [(split, i) for split in SPLITS for i in range(counts[split])
            if not (out_dir / f"{split}.h5").is_file() and not _part_path(parts, split, i).is_file()]
    tasks = [(cfg, split, i, int(seed), num_frames, str(parts), arch) for split, i in todo]
    if tasks:
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), desc=f"{cfg['name']} -> {out_dir}", unit="traj", disable=not progress)
        if workers <= 1:
            for task in tasks:
                _simulate(task)
                bar.update()
        else:
            with multiprocessing.get_context("spawn").Pool(min(workers, len(tasks))) as pool:
                for _ in pool.imap_unordered(_simulate, tasks):
                    bar.update()
        bar.close()

    num_particles_max = 0
    for split in SPLITS:  # assemble each split once all its parts exist
        path = out_dir / f"{split}.h5"
        if not path.is_file():
            write_split(path, (_load_part(parts, split, i) for i in range(counts[split])))
        with Split(path) as data:
            if len(data) != counts[split]:
                raise DatasetError(f"{path}: {len(data)} trajectories, expected {counts[split]}")
            num_particles_max = max([num_particles_max] + [shape[1] for shape in data.shapes])
    with Split(out_dir / "train.h5") as train:
        statistics = compute_statistics(train)
        regime = regime_summary(train, float(cfg["connectivity_radius"]))
    metadata = {
        "bounds": cfg["bounds"],
        "sequence_length": num_frames - 1,
        "default_connectivity_radius": cfg["connectivity_radius"],
        "dim": cfg["dim"],
        "dt": cfg["dt"],
        **statistics,
        "num_particles_max": num_particles_max,
        "gravity": cfg["gravity"],
        "regime": regime,
        "generator": generator,
    }
    write_metadata(out_dir, metadata)
    shutil.rmtree(parts, ignore_errors=True)
    return out_dir


def main(argv: Sequence[str] | None = None) -> Path:
    argv = list(sys.argv[1:] if argv is None else argv)
    if any(arg in ("-h", "--help") for arg in argv):
        scenes = sorted(p.stem for p in (package_config_dir() / "scene").glob("*.yaml"))
        print(__doc__)
        print("scenes:", ", ".join(scenes))
        return Path()
    cfg = compose(argv)
    return generate_dataset(cfg.scene, cfg.out_dir, num_trajectories=cfg.num_trajectories,
                            num_frames=cfg.num_frames, seed=cfg.seed, workers=cfg.workers, arch=cfg.arch,
                            splits=dict(cfg.splits))


if __name__ == "__main__":
    main()
