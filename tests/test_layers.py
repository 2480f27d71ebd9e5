"""The packages of rgns import one way, downwards: physics <- data <- nn <- models <- training
<- evaluation <- inverse (README, Layout)."""
from __future__ import annotations

import ast
from pathlib import Path

ORDER = ["physics", "data", "nn", "models", "training", "evaluation", "inverse"]
SRC = Path(__file__).resolve().parents[1] / "src" / "rgns"


def imported_packages(path: Path) -> set[str]:
    """The rgns packages a module imports, anywhere in it (function-level imports included)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = [node.module] if isinstance(node, ast.ImportFrom) and node.module else \
            [alias.name for alias in node.names] if isinstance(node, ast.Import) else []
        for name in names:
            parts = name.split(".")
            if parts[0] == "rgns" and len(parts) > 1 and parts[1] in ORDER:
                found.add(parts[1])
    return found


def test_every_import_points_down():
    upward = []
    for package in ORDER:
        for path in sorted((SRC / package).rglob("*.py")):
            for other in imported_packages(path):
                if ORDER.index(other) > ORDER.index(package):
                    upward.append(f"{path.relative_to(SRC)} imports rgns.{other}")
    assert not upward, upward
