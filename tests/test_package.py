"""rgns as a library: the wheel holds the configs, and an installed copy (not the repo) generates
data and composes configs from a folder outside the repository."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

import rgns
from rgns.data.contract import open_split, validate_dataset

ROOT = Path(__file__).resolve().parents[1]
BUILD_INPUTS = ["pyproject.toml", "README.md", "src", "conf"]  # all that pyproject.toml reads


def run(*args, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"} | {"OMP_NUM_THREADS": "1"}
    done = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{args}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """Build the wheel from a copy of the repo and install it, alone, into a fresh venv.

    Returns ``(wheel, python)``; that python imports the installed rgns and reuses this
    environment's torch and other dependencies."""
    tmp = tmp_path_factory.mktemp("package")
    tree = tmp / "tree"  # a copy, so the build writes nothing into the repo
    tree.mkdir()
    for name in BUILD_INPUTS:
        source = ROOT / name
        if source.is_dir():  # symlinks=True keeps src/rgns/conf a link to the copy's conf/
            shutil.copytree(source, tree / name, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(source, tree / name)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check"]
    run(*pip, "wheel", "--no-deps", "--no-build-isolation", "--no-index", tree, "-w", tmp / "wheels", cwd=tmp)
    (wheel,) = (tmp / "wheels").glob("rgns-*.whl")

    venv = tmp / "venv"
    run(sys.executable, "-m", "venv", "--without-pip", "--system-site-packages", venv, cwd=tmp)
    python = venv / ("Scripts" if os.name == "nt" else "bin") / "python"
    site = Path(run(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])", cwd=tmp).stdout.strip())
    # A venv made from a venv sees the base interpreter's site-packages, not this one's: name
    # this environment's after the new venv's own (plain lines: its editable-install .pth, which
    # would put the repo's src/ on the path, is not run).
    ours = dict.fromkeys(sysconfig.get_paths()[key] for key in ("purelib", "platlib"))
    (site / "_rgns_test_parent_env.pth").write_text("\n".join(ours) + "\n")
    run(*pip, "--python", python, "install", "--no-deps", "--no-index", "--ignore-installed", wheel, cwd=tmp)
    return wheel, python


def test_the_wheel_ships_every_config(installed):
    wheel, _ = installed
    shipped = {name for name in zipfile.ZipFile(wheel).namelist() if name.startswith("rgns/conf/")}
    configs = {f"rgns/conf/{path.relative_to(rgns.config_dir()).as_posix()}"
               for path in rgns.config_dir().rglob("*.yaml")}
    assert {"rgns/conf/train.yaml", "rgns/conf/generate.yaml", "rgns/conf/scene/waterdrop.yaml"} <= configs
    assert configs <= shipped, sorted(configs - shipped)
    assert "rgns/conf/__init__.py" in shipped  # what Hydra needs for pkg://rgns.conf


COMPOSE = """
import inspect
import json
from hydra import compose, initialize_config_dir, initialize_config_module
from hydra.utils import get_class
import rgns
with initialize_config_dir(str(rgns.config_dir()), version_base="1.3"):
    by_dir = compose("train", overrides=["output_dir=out", "model=gns", "loss=dl1"])
with initialize_config_module("rgns.conf", version_base="1.3"):
    by_module = compose("train", overrides=["output_dir=out", "model=gns", "loss=dl1"])
print(json.dumps({"rgns": rgns.__file__, "config_dir": str(rgns.config_dir()),
                  "model": by_dir.model._target_, "model_file": inspect.getfile(get_class(by_dir.model._target_)),
                  "loss": by_dir.loss.name, "same": by_dir == by_module}))
"""


def test_the_installed_package_composes_its_configs(installed, tmp_path):
    _, python = installed
    venv = python.parents[1]
    found = json.loads(run(python, "-c", COMPOSE, cwd=tmp_path).stdout.strip().splitlines()[-1])
    for key in ("rgns", "config_dir", "model_file"):  # the installed copy, not the repo's src/ or conf/
        assert Path(found[key]).is_relative_to(venv) and not Path(found[key]).is_relative_to(ROOT), found
    assert found["model"] == "rgns.models.GNS" and found["loss"] == "DL1"
    assert found["same"]  # pkg://rgns.conf and rgns.config_dir() are the same configs


def test_the_installed_package_generates_a_dataset(installed, tmp_path):
    _, python = installed
    out_dir = tmp_path / "waterdrop"
    run(python, "-m", "rgns.data.generate", "scene=waterdrop", f"out_dir={out_dir}", "num_trajectories=1",
        "num_frames=8", "splits.valid=1", "splits.test=1", "workers=1", cwd=tmp_path)
    assert sorted(p.name for p in out_dir.iterdir()) == ["metadata.json", "test.h5", "train.h5", "valid.h5"]
    assert list(tmp_path.iterdir()) == [out_dir]  # nothing else written to the cwd
    metadata = validate_dataset(out_dir)
    assert metadata["sequence_length"] == 7
    assert metadata["generator"]["num_trajectories"] == {"train": 1, "valid": 1, "test": 1}
    with open_split(out_dir, "train") as train:
        assert len(train) == 1 and train[0].position.shape[0] == 8
