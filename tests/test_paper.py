"""The paper's tables across benchmarks (``python -m rgns.paper``) on tiny checkpoints:
the three tables, the ablation figure and the JSON are written; mean ± std over planted per-seed
results; a benchmark without a dataset and a method without checkpoints are reported as not
trained; a rerun takes every evaluation from the cache."""
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
from conftest import make_metadata, random_trajectory

from rgns.data.contract import SPLITS, write_metadata, write_split
from rgns import paper
from rgns.evaluation.report import number

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="1")
FRAMES = 30
TINY = ["evaluate.trajectories=1", "evaluate.task.forward.steps=8", "+evaluate.task.forward.distribution_steps=[1]",
        "+evaluate.task.efficiency.repeats=1", "+evaluate.task.efficiency.memory=false",
        "evaluate.task.inverse.horizons=[1,6]", "evaluate.task.inverse.table_horizon=6",
        "evaluate.task.inverse_optimisation.horizons=[1,6]", "evaluate.task.inverse_optimisation.table_horizon=6",
        "+evaluate.task.inverse_optimisation.rule.max_iterations=3", "optimisers.mpm=null",
        "~benchmarks.water3d", "~benchmarks.sand"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A 30-frame dataset (its SPH spacing recorded, so that SPH + Adam runs on it) and two tiny
    R-GNS runs, seeds 0 and 1, 4 training steps each, at runs/rgns/seed<N>/."""
    root = tmp_path_factory.mktemp("paper")
    data = root / "data"
    rng = np.random.default_rng(0)
    for split, count in zip(SPLITS, (2, 1, 1)):
        write_split(data / f"{split}.h5", [random_trajectory(rng, frames=FRAMES) for _ in range(count)])
    write_metadata(data, dict(make_metadata(frames=FRAMES), generator=dict(params=dict(spacing=0.02))))
    subprocess.run(
        [sys.executable, "train.py", "-m", "data=folder", f"data.root={data}", "model=rgns", "seed=0,1",
         "model.latent=16", "model.layers=2", "trainer=cpu", "trainer.max_steps=4", "trainer.val_check_interval=4",
         "data.num_workers=0", "logger=tensorboard", f"hydra.sweep.dir={root / 'sweep'}"],
        cwd=ROOT, env=ENV, check=True, capture_output=True, timeout=300)
    for run in (root / "sweep").iterdir():
        if (run / ".hydra").is_dir():
            seed = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())["seed"]
            shutil.move(run, root / "runs" / "rgns" / f"seed{seed}")
    return root


def plant(folder: Path, label: str, seed: int, **numbers) -> Path:
    """A results.json as evaluate.py writes it, holding one method with the given summary numbers."""
    summary = dict(parameters=1000, forward_ms_per_step=2.0, memory_mb=3.0) | numbers
    results = dict(methods={label: dict(source=f"planted seed {seed}", seed=seed)},
                   datasets={"data": dict(summary={label: summary},
                                          forward=dict(settings=dict(trajectories=1, steps=8, start=5)))})
    path = folder / f"seed{seed}" / "results.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(results))
    return path


def run(trained: Path, tmp_path: Path, *extra: str) -> dict:
    """The command; run from ``tmp_path`` (monkeypatch.chdir), the manifest's own globs find nothing."""
    return paper.main([f"out_dir={tmp_path / 'out'}", f"cache_dir={tmp_path / 'cache'}", *TINY,
                       f"benchmarks.waterdrop.data={trained / 'data'}",
                       f"benchmarks.waterramps.data={tmp_path / 'no_such_dataset'}", *extra])


def table_rows(markdown: str, heading: str, first: str | None = None) -> dict[str, dict[str, str]]:
    """The first table after ``heading`` (whose top-left cell is ``first``, where given):
    {first cell of each row: {column: cell}}."""
    tables, current = [], []
    for line in markdown.split(heading, 1)[1].splitlines() + [""]:
        if line.startswith("|---"):
            continue
        if line.startswith("|"):
            current.append([c.strip() for c in line.strip().strip("|").split("|")])
        elif current:
            tables.append(current)
            current = []
    header, *rows = next(t for t in tables if first is None or t[0][0] == first)
    return {row[0]: dict(zip(header[1:], row[1:])) for row in rows}


def test_tables_figures_and_json_from_checkpoints_and_a_cached_rerun(trained, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    evaluations = []
    real = paper.evaluate

    def counted(cfg):
        evaluations.append(cfg.ckpt_path)
        return real(cfg)

    monkeypatch.setattr(paper, "evaluate", counted)
    rgns = str(trained / "runs" / "rgns" / "*" / "checkpoints" / "best*.ckpt")
    gns = [plant(tmp_path / "planted", "GNS 8x2", seed, rollout_mse=value)
           for seed, value in ((0, 2e-3), (1, 5e-3))]
    manifest = [f"benchmarks.waterdrop.sets.main.methods.rgns=['{rgns}']",
                f"benchmarks.waterdrop.sets.main.methods.gns=['{tmp_path / 'planted' / 'seed*' / 'results.json'}#GNS 8x2']",
                "~benchmarks.waterdrop.sets.shipped", f"benchmarks.waterdrop.ablation.dl4=['{rgns}']",
                f"benchmarks.waterdrop.ablation.dl1=['{gns[0]}#GNS 8x2']"]
    first = run(trained, tmp_path, *manifest)
    assert sorted(Path(p).parent.parent.name for p in evaluations) == ["seed0", "seed1"]  # each checkpoint once

    out = tmp_path / "out"
    for name in ("tables.md", "paper.json", "rollout_mse.png", "accuracy_vs_speed.png", "ablation.png"):
        assert (out / name).stat().st_size > 0, name
    saved = json.loads((out / "paper.json").read_text())
    assert saved["benchmarks"]["waterdrop"]["sets"]["main"]["methods"]["rgns"]["seeds"] == [0, 1]
    bench = first["benchmarks"]["waterdrop"]
    rgns_entry = bench["sets"]["main"]["methods"]["rgns"]
    # each run's number is its cached evaluation's, and the cell is their mean ± sample std
    values = []
    for item in rgns_entry["runs"]:
        results = json.loads((Path(item["cache"]) / "results.json").read_text())
        (summary,) = [row for label, row in results["datasets"]["data"]["summary"].items() if label == item["label"]]
        values.append(summary["rollout_mse"])
        assert item["inverse_optimisation"]["horizon"] == 6
    assert rgns_entry["rollout_mse"]["mean"] == pytest.approx(np.mean(values))
    assert rgns_entry["rollout_mse"]["std"] == pytest.approx(np.std(values, ddof=1))

    markdown = (out / "tables.md").read_text()
    for heading in ("## Table 1", "## Table 2", "## Table 3: inverse at K = 6", "## Ablations"):
        assert heading in markdown
    table1 = table_rows(markdown, "## Table 1")
    row = table1["waterdrop (main budget)"]
    assert row["R-GNS"] == paper.cell(rgns_entry["rollout_mse"], 1e3) and row["R-GNS"].endswith("(2)")
    assert row["NeuralSPH"] == "not trained"  # the main job trains R-GNS, GNS and Sep-GNS only
    baselines = table1["waterdrop (baselines budget)"]
    assert baselines["NeuralSPH"] == "not trained" and "no checkpoint matches `outputs/baselines/2*/train/s*/neural_sph" in markdown
    assert row["Const. velocity"] == number(bench["yardsticks"]["constant_velocity"]["rollout_mse"], 1e3)
    assert set(table1["waterramps"].values()) >= {"not trained"}
    assert f"waterramps: no dataset: {tmp_path / 'no_such_dataset'} lacks metadata.json, test.h5" in markdown
    table3 = table_rows(markdown, "## Table 3")
    assert table3["R-GNS (main budget)"]["Max stable steps"].count("/") == 1  # one cell per run
    sph = [label for label in table3 if label.startswith("SPH + Adam")]
    assert len(sph) == 1 and bench["optimisers"]["methods"]["SPH + Adam"]["horizons_run"] == [1, 6]
    ablation = table_rows(markdown, "## Ablations", "Variant")
    assert ablation["DL_4"]["Rollout MSE (1e-3)"] == row["R-GNS"] and ablation["DL_2"]["Rollout MSE (1e-3)"] == "not trained"
    assert ablation["DL_1"]["Rollout MSE (1e-3)"] == f"{number(2e-3, 1e3)} (1)"  # one run: no spread

    # the rerun: every checkpoint, the yardsticks and the optimisers from the cache
    evaluations.clear()
    monkeypatch.setattr(paper, "compare_inverse", lambda *a, **k: pytest.fail("optimisers run again"))
    again = run(trained, tmp_path, *manifest)
    assert evaluations == []
    bench = again["benchmarks"]["waterdrop"]
    assert bench["yardsticks"]["cached"] and bench["optimisers"]["cached"]
    assert bench["sets"]["main"]["methods"]["rgns"]["rollout_mse"] == rgns_entry["rollout_mse"]


def test_mean_and_std_over_planted_seeds_and_what_is_not_trained(trained, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    values = {0: 1.0e-3, 1: 2.0e-3, 2: 4.5e-3}
    for seed, value in values.items():
        plant(tmp_path / "rgns", "R-GNS 8x2", seed, rollout_mse=value, consistency_mse=value / 10, parameters=500)
    result = run(trained, tmp_path, "optimisers.sph=null",
                 f"benchmarks.waterdrop.sets.main.methods.rgns=['{tmp_path / 'rgns' / 'seed*' / 'results.json'}#R-GNS 8x2']",
                 "benchmarks.waterdrop.sets.main.methods.gns=[]", "~benchmarks.waterdrop.sets.shipped")
    entry = result["benchmarks"]["waterdrop"]["sets"]["main"]["methods"]["rgns"]
    expected = list(values.values())
    assert entry["seeds"] == [0, 1, 2] and entry["rollout_mse"]["n"] == 3
    assert entry["rollout_mse"]["mean"] == pytest.approx(np.mean(expected))
    assert entry["rollout_mse"]["std"] == pytest.approx(np.std(expected, ddof=1))
    markdown = (tmp_path / "out" / "tables.md").read_text()
    cell = table_rows(markdown, "## Table 1")["waterdrop (main budget)"]["R-GNS"]
    assert cell == f"{number(np.mean(expected), 1e3)} ± {number(np.std(expected, ddof=1), 1e3, 2)} (3)"
    assert cell == "2.5 ± 1.8 (3)"
    gns = result["benchmarks"]["waterdrop"]["sets"]["main"]["methods"]["gns"]
    assert gns["status"] == "not trained" and gns["reason"] == "no checkpoint listed in the manifest"
    assert result["benchmarks"]["waterramps"]["status"] == "not trained"
    assert "solver + Adam: not run (no optimiser in the manifest (optimisers))" in markdown
