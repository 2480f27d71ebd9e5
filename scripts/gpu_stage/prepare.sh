#!/bin/bash
# Builds .gpu/ (git-ignored through .git/info/exclude) for scripts/gpu_stage/run.sh on a GPU machine
# whose Python has torch, Lightning and PyG but not Hydra, and that a 64 MiB copy of the tree must
# reach: Hydra, OmegaConf and ANTLR's runtime (pure Python) copied from .venv, the first N training
# trajectories of a dataset and its validation and test splits packed losslessly (codec.py, ~3.7x).
# usage: bash scripts/gpu_stage/prepare.sh [DATASET=datasets/waterdrop_train256] [N=128]
set -eu
DATA=${1:-datasets/waterdrop_train256}; N=${2:-128}
grep -qx '/.gpu/' .git/info/exclude || echo '/.gpu/' >> .git/info/exclude
mkdir -p .gpu/site .gpu/data
SP=$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
cp -r "$SP/hydra" "$SP/omegaconf" "$SP/antlr4" .gpu/site/
find .gpu/site -name __pycache__ -prune -exec rm -rf {} +
.venv/bin/python scripts/gpu_stage/codec.py pack "$DATA/train.h5" .gpu/data/train.xzd "$N"
.venv/bin/python scripts/gpu_stage/codec.py pack "$DATA/valid.h5" .gpu/data/valid.xzd
.venv/bin/python scripts/gpu_stage/codec.py pack "$DATA/test.h5" .gpu/data/test.xzd
cp "$DATA/metadata.json" .gpu/data/metadata.json
du -sh .gpu
