#!/usr/bin/env bash
# The main job, from a fresh clone: set up .venv, make the embedded default dataset
# (datasets/waterdrop40_main: the waterdrop scene, 32/8/8 train/valid/test trajectories), train R-GNS, GNS
# and Sep-GNS on the CPU (experiment=main), evaluate them beside the yardsticks (the dataset's
# solver at coarser grids, its predictability floor, ballistic motion with walls, constant
# velocity) and write the report.
#
# Two training processes run side by side, one thread each (a 2-core machine): R-GNS then Sep-GNS
# on one, GNS on the other, each with a step budget that fits its share of the time (capped by
# trainer.max_time as well). Every phase's wall time goes to <out>/timing.md.
# Usage: bash scripts/main.sh [BENCHMARK] [extra train.py overrides for every model, e.g. seed=1]
#   BENCHMARK: waterdrop (the default scene; outputs/main/<time>/) or another scene of conf/scene --
#   waterramps, water3d, sand -- trained the same way on its own datasets/<BENCHMARK>40_main
#   (outputs/main_<BENCHMARK>/<time>/; the layout conf/paper.yaml reads)
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/lib.sh
benchmark=waterdrop
if [[ $# -gt 0 && $1 != *=* ]]; then benchmark=$1; shift; fi
check_benchmark scripts/main.sh "$benchmark"
bash scripts/setup.sh
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONWARNINGS=ignore
data="datasets/${benchmark}40_main"
if [[ $benchmark == waterdrop ]]; then runs=outputs/main; else runs="outputs/main_$benchmark"; fi
out="$runs/$(date +%Y-%m-%d_%H-%M-%S)"
mkdir -p "$out/train"
timing="$out/timing.md"
phase_start=$SECONDS
phase() {  # phase NAME: the wall time since the previous phase ended
  echo "| $1 | $((SECONDS - phase_start)) s |" >> "$timing"
  phase_start=$SECONDS
}
printf '| phase | wall time |\n|---|---|\n' > "$timing"

echo "== 1/3 dataset: $data (the $benchmark scene, 32/8/8 trajectories)"
.venv/bin/python -m rgns.data.generate scene="$benchmark" num_trajectories=32 splits.valid=8 splits.test=8 \
  out_dir="$data"
phase "dataset (generated, or found complete)"

# model, its steps and its time cap; the budgets come from docs/main_job.md's measurements
train() {  # train FOLDER MODEL STEPS CAP [EXPERIMENT] [overrides]: experiment=main unless another is given
  local folder=$1 model=$2 steps=$3 cap=$4 experiment=main; shift 4
  [[ ${1:-} == experiment=* ]] && { experiment=${1#experiment=}; shift; }
  # into a log file: progress lines (callbacks.time_split) instead of a progress bar redrawn every step
  .venv/bin/python train.py experiment="$experiment" model="$model" trainer.max_steps="$steps" trainer.max_time="$cap" \
    trainer.enable_progress_bar=false data.root="$data" data.make_root="$data" data.make.scene="$benchmark" \
    hydra.run.dir="$out/$folder/$model" "$@" > "$out/$folder/$model.log" 2>&1
}
# the second stage of R-GNS and GNS (conf/experiment/main_stage.yaml): pushes of up to 40 steps, the
# loss unrolled through 6, the density term; from the base run's checkpoint that PICK names: best (its
# best validation) or last (its end: GNS's validations are level from the first, every 2,500 steps,
# so its best is a draw of the noise: on seed 0 the first, step 2,500 of 11,791; docs/main_job.md)
stage() {  # stage MODEL PICK [overrides]
  local model=$1 pick=$2 init; shift 2
  if [[ $pick == last ]]; then init="$out/base/$model/checkpoints/last.ckpt"
  else init="$(ls "$out/base/$model"/checkpoints/best-step*.ckpt | head -n 1)"; fi
  train train "$model" 600 00:00:04:00 experiment=main_stage init_from="$init" "$@"
}
mkdir -p "$out/base"
echo "== 2/3 training -> $out/train (R-GNS, then Sep-GNS | GNS; bases in $out/base; logs: <folder>/<model>.log)"
# sizes and recipes per model: docs/main_job.md (equal message-passing steps: R-GNS's 2 blocks hold
# 4 couplings, GNS has 4 interaction layers; pushforward helped GNS's base)
# (R-GNS and GNS: a base run with the one-step loss (GNS: pushforward), then the 600-step stage
# that keeps the water's density (main_stage); Sep-GNS one run. Each base's checkpoint is chosen
# at its validations (every 2,500 steps); the caps, not the step counts, end the bases on a 2-core
# machine (R-GNS near step 6,500, GNS near 11,800) and the stages (near step 450-500))
# (R-GNS without the memory-saving backward: plain autograd is 1.4x the steps/s at this size on a CPU;
# R-GNS and GNS compiled (module.compile): 1.4-2x their eager steps/s in this job after 1-2 min of
# compilation; Sep-GNS's short run stays eager; docs/main_job.md)
# (pair terms that cancel, momentum conserved away from the walls: R-GNS's couplings=pairwise and
# GNS's decoder=pairwise, with gravity as their reference; the three-seed study in docs/main_job.md)
rgns=(model.memory_saving=false module.compile=true model.couplings=pairwise)
gns=(model.layers=4 module.compile=true model.decoder=pairwise)
( train base rgns 7500 00:00:07:00 "${rgns[@]}" "$@" && stage rgns best "${rgns[@]}" "$@" \
  && train train sep_gns 5000 00:00:04:00 model.layers=4 recipe=pushforward model.decoder=pairwise "$@" ) &
first=$!
( train base gns 15000 00:00:11:00 "${gns[@]}" recipe=pushforward "$@" && stage gns last "${gns[@]}" "$@" ) &
second=$!
status=0
wait $first || status=$?
wait $second || status=$?
for log in "$out"/base/*.log "$out"/train/*.log; do
  [ -f "$log" ] && grep -h "^\[time\]" "$log" | sed "s|^|${log#$out/}: |" || true
done
if [ "$status" -ne 0 ]; then
  echo "training failed (exit $status): see $out/train/*.log" >&2
  exit "$status"
fi
phase "training, both processes (each run's own split of steps and validation: $out/train/<model>/timing.json)"

echo "== 3/3 evaluation -> $out/evaluation"
# every forward metric on all 8 test trajectories, the rollouts in two processes (workers=2: the
# networks' in a forked copy and here, the solver references here); the inverse at K = 1, 5, 20 and the table's 40;
# beside the fresh models, the long-trained ones that are there, labelled "pretrained" (docs/pretrained.md):
# R-GNS and GNS from pretrained/waterdrop40_main_64/ (the recipe study's shipped files, R-GNS 128x2 and
# GNS 64x4), R-GNS† and Sep-GNS from pretrained/waterdrop40_main/ (32 wide, scripts/pretrain.sh); the
# fresh models are also rolled out without their hard walls, the pretrained ones with them only
# (without_hard_walls=fresh: their twins would cost about a minute of the 25); data_root: this
# checkout's dataset for all of them (a checkpoint records the absolute dataset path of the machine
# that trained it; the generator makes the same bytes everywhere)
# (another benchmark: its files under pretrained/<benchmark>/, where there are any)
if [[ $benchmark == waterdrop ]]; then
  pretrained=$(ls pretrained/waterdrop40_main_64/{rgns,gns}.ckpt pretrained/waterdrop40_main/{rgns_forward_only,sep_gns}.ckpt \
    2>/dev/null | paste -sd, - || true)
else
  pretrained=$(ls pretrained/"$benchmark"/*.ckpt 2>/dev/null | paste -sd, - || true)
fi
.venv/bin/python evaluate.py checkpoints_dir="$out/train" checkpoint=best trajectories=8 workers=2 \
  'task.inverse.horizons=[1,5,20,40]' "pretrained=[$pretrained]" without_hard_walls=fresh \
  data_root="$data" hydra.run.dir="$out/evaluation"
phase "evaluation"

ln -sfn "$(basename "$out")" "$runs/latest"
echo "Report: $out/evaluation/report.md (also $runs/latest/evaluation/report.md)"
echo "Time per phase: $timing"
echo "TensorBoard: .venv/bin/tensorboard --logdir $out/train"
