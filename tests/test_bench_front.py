"""``python -m rgns.bench front``: the fronts, the solver's cost at a learned model's accuracy, the
marks, and a whole run on a tiny generated dataset."""
from __future__ import annotations

import json
import math

import pytest
import torch

from rgns.bench.front import analyse, cost_at, main, report
from rgns.data.generate import generate_dataset, scene_config
from rgns.evaluation.metrics import mse_per_step
from rgns.evaluation.methods import find_checkpoints, load_checkpoints
from rgns.evaluation.plots import pareto_front
from rgns.evaluation.tasks import Dataset
from rgns.training.module import SimulatorModule


def test_pareto_front_keeps_what_no_cheaper_point_beats():
    points = [(4.0, 1e-4, "fine"), (1.0, 1e-2, "coarse"), (2.0, 2e-2, "worse and dearer"), (2.0, 1e-3, "mid"),
              (8.0, 1e-4, "as good, dearer")]
    assert [p[2] for p in pareto_front(points)] == ["coarse", "mid", "fine"]


def test_cost_at_interpolates_log_log_and_bounds_beyond_the_ends():
    solver = [(1.0, 1e-2, "coarse"), (4.0, 1e-4, "fine")]
    relation, ms = cost_at(solver, 1e-3)  # half way in log(mse): half way in log(ms)
    assert relation == "=" and ms == pytest.approx(2.0)
    assert cost_at(solver, 1e-2) == ("=", 1.0)
    assert cost_at(solver, 1e-1) == ("<", 1.0)  # worse than the cheapest solver: cheaper than it, at most
    assert cost_at(solver, 1e-6) == (">", 4.0)  # better than the finest measured: dearer than it, at least
    with pytest.raises(ValueError, match="no solver"):
        cost_at([], 1e-3)


def row(ms, mse, learned, parameters=0, **settings):
    return dict(ms_per_frame=ms, rollout_mse=mse, learned=learned, source="x", parameters=parameters,
                settings=settings or None)


def test_analyse_finds_the_half_resolution_solver_the_fastest_good_model_and_the_front():
    rows = {"MPM 32": row(0.5, 4e-4, False, n_grid=32, stored_n_grid=64, perturbation=None),
            "MPM 48": row(0.8, 1e-4, False, n_grid=48, stored_n_grid=64, perturbation=None),
            "floor": row(1.0, 1e-8, False, n_grid=64, stored_n_grid=64, perturbation=1e-4),
            "big": row(40.0, 3e-4, True, 9000), "small": row(8.0, 4e-4, True, 2000),
            "fast bad": row(0.2, 5e-3, True, 100)}
    analysis = analyse(rows, "big")
    marks = analysis["marks"]
    assert marks["half_resolution"] == "MPM 32" and marks["fastest_at_most_half_resolution_mse"] == "small"
    assert marks["reference_over_fastest"] == pytest.approx(5.0) and marks["on_solver_front"] == []
    assert analysis["learned_front"] == ["fast bad", "small", "big"]
    assert analysis["smallest_within"] == "small"  # 4e-4 is within 1.5x of 3e-4; 5e-3 is not
    assert analyse(rows, "big", within=1.2)["smallest_within"] == "big"
    assert analysis["solver_front"] == ["MPM 32", "MPM 48", "floor"]
    assert analysis["against_solver"]["fast bad"]["relation"] == "<"
    big = analysis["against_solver"]["big"]
    assert big["relation"] == "=" and 0.5 < big["solver_ms_at_same_mse"] < 0.8
    assert big["ratio"] == pytest.approx(40.0 / big["solver_ms_at_same_mse"])
    text = report(rows, analysis)
    assert "fastest learned model at most its rollout MSE: small" in text and "5.00x" in text
    rows["quick"] = row(0.4, 3.9e-4, True)  # at most the half-resolution error, in less of its time
    assert analyse(rows, "big")["marks"]["on_solver_front"] == ["quick"]


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    cfg = scene_config("waterdrop")
    cfg["splits"] = {"train": 1, "valid": 1, "test": 1}
    root = generate_dataset(cfg, tmp_path_factory.mktemp("front") / "waterdrop", num_frames=14, seed=3, workers=1,
                            progress=False)
    from rgns.data.datamodule import ParticleDataModule
    datamodule = ParticleDataModule(str(root))
    datamodule.prepare_data()
    module = SimulatorModule(model={"_target_": "rgns.models.GNS", "latent": 8, "layers": 1},
                             metadata=datamodule.metadata, loss={"_target_": "rgns.training.losses.LossDesign", "mse": 1.0},
                             optimizer={"_target_": "torch.optim.Adam", "_partial_": True})
    checkpoint = root.parent / "gns.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams), "global_step": 0,
                "data_root": str(root)}, checkpoint)
    return root, checkpoint


def test_a_run_measures_models_and_solvers_on_the_same_frames(generated, tmp_path, capsys):
    root, checkpoint = generated
    out = tmp_path / "front.json"
    main(["--checkpoints", str(checkpoint), "--data-root", str(root), "--trajectories", "1", "--steps", "6",
          "--resolutions", "0.5", "--reference", str(checkpoint), "--precision", "float32", "bfloat16",
          "--json", str(out)])
    result = json.loads(out.read_text())
    rows = result["rows"]
    label = "GNS 8x1"
    assert set(rows) == {label, f"{label} bf16", "MPM 32 cells/m", "MPM floor (1e-4 m)"}
    assert rows[f"{label} bf16"]["rollout_mse"] != rows[label]["rollout_mse"]  # the other arithmetic
    assert result["analysis"]["marks"].get("reference", label) == label  # the float32 one is the reference
    assert all(r["ms_per_frame"] > 0 and math.isfinite(r["rollout_mse"]) for r in rows.values())
    # the learned model's error is its evaluation rollout's, on frames 6..11
    (method,) = load_checkpoints(find_checkpoints(ckpt_paths=[str(checkpoint)]))
    dataset = Dataset.load(str(root), "test", 1, method.model.history, None)
    position = dataset.trajectories[0][0]
    expected = float(mse_per_step(method.forward_rollout(dataset, 0, 6), position[6:12]).mean())
    assert rows[label]["rollout_mse"] == pytest.approx(expected, rel=1e-5)
    assert result["analysis"]["marks"]["half_resolution"] == "MPM 32 cells/m"
    assert rows["MPM 32 cells/m"]["settings"]["n_grid"] == 32 and rows["MPM floor (1e-4 m)"]["settings"]["perturbation"] == 1e-4
    assert "half-resolution solver: MPM 32 cells/m" in capsys.readouterr().out


def test_a_dataset_without_a_solver_is_refused_with_the_reason(generated, tmp_path):
    root, checkpoint = generated
    converted = tmp_path / "converted"
    converted.mkdir()
    for name in ("train.h5", "valid.h5", "test.h5"):
        (converted / name).write_bytes((root / name).read_bytes())
    metadata = json.loads((root / "metadata.json").read_text())
    metadata.pop("generator")
    (converted / "metadata.json").write_text(json.dumps(metadata))
    with pytest.raises(SystemExit):
        main(["--checkpoints", str(checkpoint), "--data-root", str(converted), "--trajectories", "1", "--steps", "4"])


def test_the_chart_plots_ms_per_frame_and_draws_the_learned_front(tmp_path, monkeypatch):
    import rgns.evaluation.plots as plots
    figures = []
    monkeypatch.setattr(plots, "save_figure", lambda fig, path: figures.append(fig))
    summary = {"R-GNS 8x2": dict(rollout_mse=1e-3, forward_ms_per_step=8.0, forward_ms_per_frame=2.0, parameters=10),
               "GNS 8x2": dict(rollout_mse=5e-4, forward_ms_per_step=6.0, parameters=10),
               "GNS 4x1": dict(rollout_mse=2e-3, forward_ms_per_step=9.0, parameters=5),  # dearer and worse
               "Const. velocity": dict(rollout_mse=8e-2, forward_ms_per_step=0.2, parameters=0),  # no training
               "MPM 32 cells/m": dict(rollout_mse=4e-4, forward_ms_per_step=0.5, parameters=0)}
    results = {"methods": {k: {} for k in summary},
               "datasets": {"d": {"summary": summary, "references": {"methods": {"MPM 32 cells/m": {}}}}}}
    assert plots.accuracy_vs_speed(results, tmp_path / "a.png")
    (ax,) = figures[0].axes
    (learned,) = [line for line in ax.get_lines() if line.get_label() == "learned front"]
    assert list(learned.get_xdata()) == [2.0, 6.0] and list(learned.get_ydata()) == [1e-3, 5e-4]
    assert "ms / frame" in ax.get_xlabel()
