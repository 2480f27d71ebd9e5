#!/usr/bin/env bash
# A pretrained model rebuilt from scratch by its staged recipe (docs/pretrain_recipes.md):
#
#   bash scripts/pretrain.sh BENCHMARK MODEL [seed=N] [out=DIR] [run_dir=DIR] [overwrite=true] [key=value ...]
#   bash scripts/pretrain.sh waterdrop rgns            # R-GNS 128x2 (conf/experiment/pretrain/waterdrop_rgns.yaml)
#   bash scripts/pretrain.sh waterdrop gns seed=1      # GNS 64x4   (conf/experiment/pretrain/waterdrop_gns.yaml)
#   bash scripts/pretrain.sh waterdrop rgns trainer.max_steps=20 trainer.val_check_interval=20   # a smoke run
#   bash scripts/pretrain.sh waterdrop rgns trainer=gpu                                        # on a GPU
#   bash scripts/pretrain.sh waterdrop gns preset=waterdrop_gns_stride4   # GNS on every 4th frame (longer steps)
#
# Generates the preset's dataset when missing, runs every stage (outputs/pretrain/<preset>_seed<N>/<stage>/),
# each from the previous stage's checkpoint, skips finished stages and goes on with a stopped one when
# run again, and writes pretrained/<preset>_rebuilt/<model>.ckpt with <model>.json (provenance).
# key=value apply to every stage after the stage's own. One thread per process unless OMP_NUM_THREADS says.
set -euo pipefail
cd "$(dirname "$0")/.."
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MKL_NUM_THREADS=${MKL_NUM_THREADS:-1} PYTHONWARNINGS=${PYTHONWARNINGS:-ignore}
python=${PYTHON:-.venv/bin/python}
[ -x "$python" ] || python=python3
exec "$python" -m rgns.training.stages "$@"
