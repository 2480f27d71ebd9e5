"""``python -m rgns.bench sizes``: runs grouped by size, mean and spread over seeds, and the
smallest size within a factor of the best, on planted evaluations."""
from __future__ import annotations

import json
import os
import re
import statistics
from pathlib import Path

import pytest

from rgns.bench.sizes import group, main, pick, read_results, trained_runs

RGNS = "rgns.models.RGNS"


def method(latent: int, layers: int, seed: int, **extra) -> dict:
    overrides = ["experiment=main", "model=rgns", f"model.latent={latent}", f"model.layers={layers}", f"seed={seed}",
                 f"hydra.run.dir=outputs/sizes/{latent}x{layers}_seed{seed}", *extra.pop("overrides", [])]
    return dict(source=f"/nowhere/{latent}x{layers}_{seed}/checkpoints/best.ckpt", seed=seed, overrides=overrides,
                model={"_target_": RGNS, "latent": latent, "layers": layers, "couplings": "pairwise"},
                base_label=f"R-GNS {latent}x{layers}", pretrained=False, **extra)


def write_results(path: Path, runs: dict[tuple[int, int, int], float], parameters=None, extra_methods=None) -> Path:
    """A results.json of R-GNS runs ``{(latent, layers, seed): rollout MSE}``, the two baselines and a twin."""
    methods, summary = {}, {}
    for (latent, layers, seed), mse in runs.items():
        label = f"R-GNS {latent}x{layers} pairwise couplings (seed={seed})"
        methods[label] = method(latent, layers, seed)
        summary[label] = dict(rollout_mse=mse, parameters=(parameters or {}).get((latent, layers), latent * 100 * layers),
                              forward_ms_per_frame=latent * layers / 10 + seed, stride=1)
        twin = f"{label}, no hard walls"  # the same weights without walls: never a run of its own
        methods[twin] = dict(methods[label], hard_walls=False)
        summary[twin] = dict(summary[label], rollout_mse=1e-9)
    methods["Const. velocity"] = dict(source="baseline")
    summary["Const. velocity"] = dict(rollout_mse=1e-9, parameters=0, forward_ms_per_frame=0.01)
    methods.update(extra_methods or {})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(dict(methods=methods, datasets={"waterdrop": dict(summary=summary)})))
    return path


SWEEP = {(16, 1, 0): 9.0, (16, 1, 1): 11.0, (16, 1, 2): 10.0,
         (32, 2, 0): 2.9, (32, 2, 1): 3.1, (32, 2, 2): 3.3,
         (64, 2, 0): 2.0, (64, 2, 1): 2.2, (64, 2, 2): 2.4,
         (128, 2, 0): 2.5, (128, 2, 1): 2.6, (128, 2, 2): 2.7}


def test_runs_are_grouped_by_size_with_mean_and_spread_over_seeds(tmp_path):
    runs = trained_runs(read_results([write_results(tmp_path / "results.json", SWEEP)]))
    assert len(runs) == len(SWEEP)  # no baseline, no twin
    groups = group(runs)
    assert [(g["latent"], g["layers"], g["n"]) for g in groups] == [(16, 1, 3), (32, 2, 3), (64, 2, 3), (128, 2, 3)]
    mid = groups[2]
    values = [SWEEP[64, 2, s] for s in range(3)]
    assert mid["mean"] == pytest.approx(statistics.fmean(values)) and mid["std"] == pytest.approx(statistics.stdev(values))
    assert sorted(mid["seeds"]) == [0, 1, 2] and mid["parameters"] == 64 * 100 * 2
    assert mid["ms_per_frame"] == pytest.approx(64 * 2 / 10 + 1)  # mean of seed offsets 0, 1, 2


def test_the_smallest_size_within_the_factor_of_the_best(tmp_path):
    groups = group(trained_runs(read_results([write_results(tmp_path / "results.json", SWEEP)])))
    best, smallest = pick(groups, 1.5)
    assert (best["latent"], best["layers"]) == (64, 2)  # mean 2.2
    assert (smallest["latent"], smallest["layers"]) == (32, 2)  # mean 3.1 <= 3.3; 16x1's 10 is not
    assert pick(groups, 1.2)[1] is best  # 32x2's 3.1 > 2.64; 128x2's 2.6 is within but larger
    assert pick(groups, 1.0)[1] is best
    assert pick(groups, 5.0)[1]["latent"] == 16


def test_a_size_with_a_diverged_run_is_shown_but_not_picked(tmp_path):
    sweep = dict(SWEEP)
    sweep[32, 2, 1] = float("nan")
    groups = group(trained_runs(read_results([write_results(tmp_path / "results.json", sweep)])))
    broken = next(g for g in groups if g["latent"] == 32)
    assert not broken["complete"] and broken["mean"] == pytest.approx((2.9 + 3.3) / 2)
    assert (pick(groups, 1.5)[1]["latent"], pick(groups, 1.5)[1]["layers"]) == (64, 2)


def test_the_command_reads_folders_counts_a_checkpoint_once_and_names_the_pick(tmp_path, capsys):
    write_results(tmp_path / "eval_a" / "results.json", {k: v for k, v in SWEEP.items() if k[0] <= 32})
    write_results(tmp_path / "eval_b" / "nested" / "results.json", {k: v for k, v in SWEEP.items() if k[0] >= 32})
    out = main([str(tmp_path), "--json", str(tmp_path / "sizes.json")])
    printed = capsys.readouterr().out
    assert [g["n"] for g in out["sizes"]] == [3, 3, 3, 3]  # 32x2 in both files counts once
    assert out["picks"]["waterdrop"]["smallest_within_factor"] == "R-GNS 32x2 pairwise couplings"
    assert "smallest within 1.5x of the best: R-GNS 32x2 pairwise couplings" in printed
    row = next(line for line in printed.splitlines() if line.startswith("| R-GNS 64x2"))
    assert re.search(r"\| 2\.2 ± 0\.2 \(3\) \| 1\.00 \|", row), row
    assert json.loads((tmp_path / "sizes.json").read_text())["factor"] == 1.5


def test_runs_of_another_recipe_are_kept_apart_and_named(tmp_path):
    sweep = write_results(tmp_path / "a" / "results.json", {(32, 2, 0): 3.0, (32, 2, 1): 3.2})
    other = json.loads(sweep.read_text())
    for label in list(other["methods"]):
        if "model" in other["methods"][label]:
            other["methods"][label]["overrides"].append("recipe=pushforward")
            other["methods"][label]["source"] += ".pushforward"
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "results.json").write_text(json.dumps(other))
    groups = group(trained_runs(read_results([tmp_path])))
    assert sorted(g["name"] for g in groups) == ["R-GNS 32x2 pairwise couplings",
                                                 "R-GNS 32x2 pairwise couplings (recipe=pushforward)"]
    assert all(g["n"] == 2 for g in groups)


def test_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no results.json under this folder"):
        read_results([tmp_path])
    (tmp_path / "results.json").write_text("{")
    with pytest.raises(ValueError, match=r"results.json: not a results.json"):
        read_results([tmp_path / "results.json"])
    empty = write_results(tmp_path / "e" / "results.json", {})
    with pytest.raises(ValueError, match="no trained model's rollout MSE"):
        trained_runs(read_results([empty]))


def test_the_sweep_trains_each_model_as_the_main_jobs_base_run():
    """scripts/sizes.sh's step budget, time cap and overrides per model are scripts/main.sh's base
    run's (read from main.sh by tests/test_config.py), the size aside."""
    from test_config import main_job_runs

    script = (Path(__file__).parents[1] / "scripts" / "sizes.sh").read_text()
    for model, steps, cap, body in re.findall(r"^  (\w+)\) steps=(\d+) cap=(\S+) recipe=\(([^)]*)\) ;;", script, re.M):
        base = next(r for r in main_job_runs() if r[:2] == ["experiment=main", f"model={model}"])
        assert base[2:4] == [f"trainer.max_steps={steps}", f"trainer.max_time={cap}"], model
        size = ("model.latent=", "model.layers=")
        assert sorted(o for o in base[5:] if not o.startswith(size)) == sorted(body.split()), model
    assert {"rgns", "gns"} <= set(re.findall(r"^  (\w+)\) steps=", script, re.M))


def test_strided_runs_are_sizes_of_their_own_scored_on_the_shared_frames(tmp_path):
    """A run trained with data.stride=k groups as '<size> stride k' (its stride and scaled validation
    lengths are not another recipe), and --metric rollout_mse_shared reads the shared-frame score."""
    path = write_results(tmp_path / "results.json", {(32, 2, s): 9.0 for s in range(3)})
    result = json.loads(path.read_text())
    for label in [lbl for lbl in result["methods"] if "model" in result["methods"][lbl]]:
        if result["methods"][label].get("hard_walls") is False:
            continue
        seed = result["methods"][label]["seed"]
        strided = f"{label} stride 4"
        result["methods"][strided] = dict(result["methods"][label], source=result["methods"][label]["source"] + ".s4",
                                          overrides=[*result["methods"][label]["overrides"], "data.stride=4",
                                                     "module.val_rollout_steps=38", "module.val_consistency_steps=5"])
        result["datasets"]["waterdrop"]["summary"][strided] = dict(
            result["datasets"]["waterdrop"]["summary"][label], stride=4, rollout_mse=8.0 + seed,
            rollout_mse_shared=2.0 + seed, forward_ms_per_frame=1.0)
        result["datasets"]["waterdrop"]["summary"][label]["rollout_mse_shared"] = 3.0 + seed
    path.write_text(json.dumps(result))
    plain = group(trained_runs(read_results([path])))
    assert [(g["name"], g["stride"], g["mean"]) for g in plain] == [
        ("R-GNS 32x2 pairwise couplings", 1, pytest.approx(9.0)),
        ("R-GNS 32x2 pairwise couplings stride 4", 4, pytest.approx(9.0))]
    shared = group(trained_runs(read_results([path]), metric="rollout_mse_shared"))
    assert [g["mean"] for g in shared] == [pytest.approx(4.0), pytest.approx(3.0)]
    assert pick(shared, 1.5)[0]["stride"] == 4
    with pytest.raises(ValueError, match="metric 'mse'"):
        trained_runs(read_results([path]), metric="mse")
    # a stride-1 run with those overrides is another recipe: only a strided run's are its stride's
    result["methods"]["R-GNS 32x2 pairwise couplings (seed=0)"]["overrides"].append("module.val_rollout_steps=38")
    path.write_text(json.dumps(result))
    names = {g["name"] for g in group(trained_runs(read_results([path])))}
    assert "R-GNS 32x2 pairwise couplings (module.val_rollout_steps=38)" in names


def test_the_sweep_script_trains_each_stride_with_scaled_validation(tmp_path):
    """scripts/sizes.sh's STRIDES: names, the strided overrides, and the refusal of STAGE=1 at stride > 1."""
    import subprocess

    script = Path(__file__).parents[1] / "scripts" / "sizes.sh"
    text = script.read_text()
    assert 'module.val_rollout_steps=$(( (150 + stride - 1) / stride ))' in text
    assert "--metric rollout_mse_shared" in text
    env = dict(os.environ, STRIDES="1 4", STAGE="1", OUT=str(tmp_path / "out"))
    done = subprocess.run(["bash", str(script), "rgns"], env=env, capture_output=True, text=True)
    assert done.returncode == 2 and "STAGE=1 trains stride 1 only" in done.stderr and "stride 4" in done.stderr
    done = subprocess.run(["bash", str(script), "rgns"], env=dict(env, STRIDES="0", STAGE="0"),
                          capture_output=True, text=True)
    assert done.returncode == 2 and "stride '0' is not a positive whole number" in done.stderr
    assert not (tmp_path / "out").exists()
