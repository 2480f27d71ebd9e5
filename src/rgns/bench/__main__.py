"""Benchmarks: ``python -m rgns.bench NAME [options]`` runs ``rgns.bench.NAME.main(options)``."""
import importlib
import pkgutil
import sys

import rgns.bench


def main(argv: list[str]) -> None:
    names = sorted(m.name for m in pkgutil.iter_modules(rgns.bench.__path__) if not m.name.startswith("_"))
    if not argv or argv[0] not in names:
        sys.exit(f"usage: python -m rgns.bench {{{','.join(names)}}} [options]")
    importlib.import_module(f"rgns.bench.{argv[0]}").main(argv[1:])


if __name__ == "__main__":
    main(sys.argv[1:])
