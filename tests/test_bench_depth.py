"""``python -m rgns.bench depth``: a row per depth and model, and the table's ratios."""
from __future__ import annotations

import json

from rgns.bench.depth import CASES, main, table


def test_a_small_run_measures_every_model_at_every_depth(tmp_path, capsys):
    out, png = tmp_path / "depth.json", tmp_path / "depth.png"
    rows = main(["--depths", "2", "1", "--latent", "16", "--particles", "120", "--repeats", "1",
                 "--json", str(out), "--chart", str(png)])
    assert json.loads(out.read_text()) == rows
    assert sorted((r["case"], r["depth"]) for r in rows) == sorted((c, d) for c in CASES for d in (1, 2))
    assert all(r["peak_mb"] > 0 and r["ms"] > 0 and r["edges"] > 0 for r in rows)
    for case in CASES:  # deeper is more weights
        one, two = (next(r for r in rows if r["case"] == case and r["depth"] == d) for d in (1, 2))
        assert two["parameters"] > one["parameters"]
    printed = capsys.readouterr().out
    assert "| 1 |" in printed and "| 2 |" in printed and "R-GNS MB / GNS MB" in printed
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def planted(memory: dict[str, list[float]]) -> list[dict]:
    """Rows at depths 1, 2, 4 with the given peak MB per case."""
    return [dict(model=label, case=case, depth=depth, latent=8, parameters=1, peak_mb=mb, ms=10.0 * depth,
                 edges=1, particles=1)
            for case, label in CASES.items() for depth, mb in zip((1, 2, 4), memory[case])]


def cells(text: str, depth: int) -> list[str]:
    line = next(l for l in text.splitlines() if l.startswith(f"| {depth} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_the_table_shows_memory_growing_with_depth_where_it_grows_and_flat_where_it_is_flat():
    text = table(planted({"gns": [100, 200, 400], "rgns": [50, 50, 55], "rgns_plain": [120, 240, 480]}))
    row = cells(text, 4)  # depth, 3 x MB, 3 x ms, 3 x growth, R-GNS / GNS
    assert row[1:4] == ["400", "55", "480"]
    assert row[7:10] == ["4.00", "1.10", "4.00"]
    assert row[10] == "0.14"  # 55 / 400
    assert cells(text, 1)[7:10] == ["1.00", "1.00", "1.00"]


def test_the_table_leaves_out_ratios_without_memory():
    rows = planted({case: [None] * 3 for case in CASES})
    row = cells(table(rows), 2)
    assert row[1:4] == ["-", "-", "-"] and row[7:] == ["-"] * 4 and row[4:7] == ["20", "20", "20"]
