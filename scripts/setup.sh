#!/usr/bin/env bash
# Create .venv and install rgns with its test tools. torch is pinned to the CPU build in the
# same pip command, so pip never resolves a newer (multi-GB CUDA) torch on a CPU machine.
# On a machine with a CUDA torch already installed, use `pip install -e '.[dev]'` in that
# environment instead: the torch range in pyproject.toml keeps the installed build.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install --quiet "torch==${RGNS_TORCH_VERSION:-2.13.0}" -e '.[dev]'
.venv/bin/python -c "import torch, rgns; print(f'rgns ready: torch {torch.__version__}')"
