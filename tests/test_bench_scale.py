"""``python -m rgns.bench scale``: the scenes it builds and a small run."""
from __future__ import annotations

import json

import torch
from scipy.spatial import cKDTree

from rgns.bench.scale import block, main, moving_state


def test_the_block_fits_its_box_with_about_eighteen_neighbours_in_the_bulk():
    for dim, count in ((2, 1000), (3, 1000)):
        metadata, position = block(count, dim)
        (low, high), radius = metadata["bounds"][0], metadata["default_connectivity_radius"]
        assert position.shape == (count, dim) and low < float(position.min()) and float(position.max()) < high
        tree = cKDTree(position.numpy())
        centre = position.mean(0).numpy()
        inner = tree.query_ball_point(centre, 0.3 * float(position.max() - position.min()))
        neighbours = [len(tree.query_ball_point(position[i].numpy(), radius)) - 1 for i in inner]
        assert 12 <= sum(neighbours) / len(neighbours) <= 30


def test_the_state_moves_and_its_history_is_the_velocity_drawn():
    _, position = block(500, 2)
    state = moving_state(position, 500)
    assert torch.allclose(state.position, position)
    assert torch.allclose(state.velocity_history[:, 0], state.velocity_history[:, -1], atol=1e-7)  # float32 positions
    assert 5e-4 < float(state.velocity_history.std()) < 2e-3


def test_a_small_run_times_every_model_at_every_count(tmp_path, capsys):
    out = tmp_path / "scale.json"
    main(["--counts", "200", "400", "--dims", "2", "--steps", "1", "--no-memory", "--no-solvers", "--json", str(out)])
    rows = json.loads(out.read_text())
    assert [(r["particles"], r["dim"]) for r in rows] == [(200, 2), (200, 2), (400, 2), (400, 2)]
    assert all(r["ms_per_step"] > 0 and r["edges"] > 0 and r["peak_mb"] is None for r in rows)
    assert rows[2]["edges"] > rows[0]["edges"]
    assert "time grows as particles^" in capsys.readouterr().out


def test_the_solvers_are_timed_beside_the_models_in_2d_and_3d(tmp_path, capsys):
    out, png = tmp_path / "scale.json", tmp_path / "scale.png"
    rows = main(["--counts", "100", "200", "--steps", "1", "--json", str(out), "--chart", str(png)])
    assert json.loads(out.read_text()) == rows
    solvers = [r for r in rows if r["kind"] == "solver"]
    assert [(r["dim"], r["particles"]) for r in solvers] == [(2, 100), (2, 200), (3, 100), (3, 200)]
    assert {r["model"].split(" ")[0] for r in solvers if r["dim"] == 2} == {"MLS-MPM"}
    assert {r["model"].split(" ")[0] for r in solvers if r["dim"] == 3} == {"WCSPH"}
    assert all(r["ms_per_step"] > 0 and r["peak_mb"] > 0 and r["edges"] is None for r in solvers)
    models = [r for r in rows if r["kind"] == "model"]
    assert {(r["dim"], r["particles"]) for r in models} == {(d, n) for d in (2, 3) for n in (100, 200)}
    printed = capsys.readouterr().out
    assert "MLS-MPM (waterdrop, 10 substeps), 2D: time grows as particles^" in printed
    assert "3D, 200 particles: GNS" in printed and "the time per frame of WCSPH" in printed
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
