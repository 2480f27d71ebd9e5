"""Where methods fail across benchmarks (``python -m rgns.failures``) on tiny checkpoints: every
run is rolled out on the same generated conditions, its cells are the mean ± std of the runs' own
evaluations, the yardsticks and the methods without an inverse are in the tables, a method without
checkpoints is named, and a rerun takes every evaluation from the cache."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_paper import table_rows
from test_references import tiny

from rgns import failures
from rgns.paper import cell

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")


class _Factory:
    def __init__(self, root: Path):
        self.root = root

    def mktemp(self, name: str) -> Path:
        path = self.root / name
        path.mkdir()
        return path


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A generated waterdrop dataset (20 frames) and tiny runs on it: R-GNS seeds 0 and 1, GNS seed 0,
    4 training steps each, at runs/<model>/seed<N>/."""
    root = tmp_path_factory.mktemp("failures")
    data = tiny("waterdrop", _Factory(root), frames=20, test=1)
    for model, seeds in (("rgns", "0,1"), ("gns", "0")):
        sweep = root / f"sweep_{model}"
        subprocess.run(
            [sys.executable, "train.py", "-m", "data=folder", f"data.root={data}", f"model={model}", f"seed={seeds}",
             "model.latent=16", "model.layers=2", "trainer=cpu", "trainer.max_steps=4", "trainer.val_check_interval=4",
             "data.num_workers=0", "logger=tensorboard", f"hydra.sweep.dir={sweep}"],
            cwd=ROOT, env=ENV, check=True, capture_output=True, timeout=300)
        for run in sweep.iterdir():
            if (run / ".hydra").is_dir():
                seed = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())["seed"]
                shutil.move(run, root / "runs" / model / f"seed{seed}")
    return root, data


def run(trained, tmp_path: Path) -> dict:
    root, data = trained
    glob = str(root / "runs" / "{}" / "*" / "checkpoints" / "best*.ckpt")
    return failures.main([
        f"cache_dir={tmp_path / 'cache'}", f"generalise.out_dir={tmp_path / 'out'}", "generalise.only=[waterdrop]",
        f"benchmarks.waterdrop.data={data}", f"benchmarks.waterdrop.sets.main.methods.rgns=['{glob.format('rgns')}']",
        f"benchmarks.waterdrop.sets.main.methods.gns=['{glob.format('gns')}']",
        "benchmarks.waterdrop.sets.main.methods.sep_gns=[]",
        "generalise.task.conditions=[longer,wide_box,ramps_outside]", "generalise.task.trajectories=1",
        "generalise.task.steps=6"])


def test_runs_on_shared_conditions_mean_std_yardsticks_and_a_cached_rerun(trained, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    evaluated = []
    real = failures.evaluate

    def counted(cfg):
        evaluated.append(cfg.ckpt_path)
        return real(cfg)

    monkeypatch.setattr(failures, "evaluate", counted)
    first = run(trained, tmp_path)
    assert len(evaluated) == 6  # each checkpoint once on each condition the scene can have (no ramps here)
    bench = first["benchmarks"]["waterdrop"]
    out = tmp_path / "out"
    for name in ("generalise.md", "generalise.json", "generalise.png"):
        assert (out / name).stat().st_size > 0, name

    # every run's conditions are the yardsticks': generated once, in one shared folder
    (folder,) = (tmp_path / "cache" / "conditions").iterdir()
    assert sorted(p.name for p in folder.iterdir()) == [f"{trained[1].name}_longer", f"{trained[1].name}_wide_box"]
    yard = bench["yardsticks"]["conditions"]
    assert "no ramps" in yard["ramps_outside"]["skipped"]
    rgns = bench["methods"]["rgns"]
    assert rgns["seeds"] == [0, 1] and len(rgns["runs"]) == 2
    values = []
    for item in rgns["runs"]:
        assert len(item["caches"]) == 2  # one evaluation per condition
        (longer,) = [c["longer"] for folder in item["caches"] for results in
                     [json.loads((Path(folder) / "results.json").read_text())]
                     for c in [next(iter(results["datasets"].values()))["generalise"]["conditions"]] if "longer" in c]
        assert longer["particles"] == yard["longer"]["particles"]
        values.append(longer["methods"][item["label"]]["rollout_mse"])
    summary = bench["conditions"]["longer"]["forward"]["rgns"]
    assert summary["rollout_mse"]["mean"] == pytest.approx(np.mean(values))
    assert summary["rollout_mse"]["std"] == pytest.approx(np.std(values, ddof=1))

    markdown = (out / "generalise.md").read_text()
    forward = table_rows(markdown, "## waterdrop")
    (rgns_row,) = [r for label, r in forward.items() if label.startswith("R-GNS (")]
    assert rgns_row["longer"].startswith(cell(summary["rollout_mse"], 1e3))
    assert "ramps_outside" not in rgns_row  # skipped on a scene without ramps: no column
    assert {"Const. velocity", "Ballistic + walls", "MPM 32 cells/m"} <= set(forward)
    backward = table_rows(markdown, "Backwards in time")
    (gns_row,) = [r for label, r in backward.items() if label.startswith("GNS (")]
    assert gns_row["longer"] == "no inverse" and backward["MPM 32 cells/m"]["longer"] == "no inverse"
    (rgns_back,) = [r for label, r in backward.items() if label.startswith("R-GNS (")]
    assert rgns_back["longer"][0].isdigit()
    assert bench["methods"]["sep_gns"]["status"] == "not trained" and "Sep-GNS: not trained" in markdown

    # the rerun: every evaluation from the cache, the same numbers
    evaluated.clear()
    monkeypatch.setattr(failures.Generalisation, "__call__", lambda *a, **k: pytest.fail("yardsticks again"))
    again = run(trained, tmp_path)
    assert evaluated == []
    assert again["benchmarks"]["waterdrop"]["conditions"] == bench["conditions"]


def test_a_benchmark_without_its_dataset_and_an_unknown_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    paper = failures.main([f"cache_dir={tmp_path / 'cache'}", f"generalise.out_dir={tmp_path / 'out'}",
                           "generalise.only=[sand]", f"benchmarks.sand.data={tmp_path / 'none'}"])
    assert paper["benchmarks"]["sand"]["status"] == "not trained"
    assert f"no dataset: {tmp_path / 'none'} lacks metadata.json, test.h5" in (tmp_path / "out" / "generalise.md").read_text()
    with pytest.raises(SystemExit, match="generalise.only names \\['moon'\\]"):
        failures.main([f"cache_dir={tmp_path / 'cache'}", "generalise.only=[moon]"])
