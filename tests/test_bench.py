"""The model benchmark runs end to end on a small scene and writes the keys the docs quote."""
from __future__ import annotations

import json

from rgns.bench.models import main


def test_models_benchmark_writes_every_key(tmp_path):
    path = tmp_path / "models.json"
    result = main(["--particles", "150", "--repeats", "1", "--json", str(path)])
    written = json.loads(path.read_text())
    assert written == json.loads(json.dumps(result))
    baselines = {"egnn", "neural_sph", "dmcf"}  # the paper's other forward baselines
    assert set(written["params"]) == {"gns", "rgns", "sep_gns"} | baselines
    assert set(written["infer_ms"]) == {"gns", "rgns_forward", "rgns_inverse"} | baselines
    assert {"gns", "rgns", "sep_gns"} | baselines <= set(written["train_ms"])
    assert {"gns", "rgns"} | baselines <= set(written["train_peak_mb"])
    assert written["params"]["sep_gns"] == 2 * written["params"]["gns"]
    assert all(v > 0 for group in ("infer_ms", "train_ms", "train_peak_mb") for v in written[group].values())
    ratios = written["ratios"]
    assert ratios["rgns_over_gns_train"] == written["train_ms"]["rgns"] / written["train_ms"]["gns"]
    assert ratios["rgns_over_gns_peak"] == written["train_peak_mb"]["rgns"] / written["train_peak_mb"]["gns"]
