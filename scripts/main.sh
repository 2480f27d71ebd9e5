#!/usr/bin/env bash
# The main job, from a fresh clone: set up .venv, make the embedded default dataset
# (datasets/waterdrop40_main: the waterdrop scene, 32/8/8 train/valid/test trajectories), train R-GNS, GNS
# and Sep-GNS on the CPU (experiment=main: a fixed budget each), evaluate them beside
# constant-velocity extrapolation, and write the report.
# Usage: bash scripts/main.sh [extra train.py overrides, e.g. trainer.max_time=00:00:02:00]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONWARNINGS=ignore
out="outputs/main/$(date +%Y-%m-%d_%H-%M-%S)"

echo "== 1/3 default dataset: datasets/waterdrop40_main (the waterdrop scene, 32/8/8 trajectories)"
.venv/bin/python -m rgns.data.generate scene=waterdrop num_trajectories=32 splits.valid=8 splits.test=8 \
  out_dir=datasets/waterdrop40_main

echo "== 2/3 training R-GNS, GNS, Sep-GNS -> $out/train"
.venv/bin/python train.py -m experiment=main model=rgns,gns,sep_gns hydra.sweep.dir="$out/train" "$@"

echo "== 3/3 evaluation -> $out/evaluation"
.venv/bin/python evaluate.py checkpoints_dir="$out/train" checkpoint=best trajectories=8 hydra.run.dir="$out/evaluation"

ln -sfn "$(basename "$out")" outputs/main/latest
echo "Report: $out/evaluation/report.md (also outputs/main/latest/evaluation/report.md)"
echo "TensorBoard: .venv/bin/tensorboard --logdir $out/train"
