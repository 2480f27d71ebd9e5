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
# Usage: bash scripts/main.sh [extra train.py overrides for every model, e.g. seed=1]
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONWARNINGS=ignore
out="outputs/main/$(date +%Y-%m-%d_%H-%M-%S)"
mkdir -p "$out/train"
timing="$out/timing.md"
phase_start=$SECONDS
phase() {  # phase NAME: the wall time since the previous phase ended
  echo "| $1 | $((SECONDS - phase_start)) s |" >> "$timing"
  phase_start=$SECONDS
}
printf '| phase | wall time |\n|---|---|\n' > "$timing"

echo "== 1/3 default dataset: datasets/waterdrop40_main (the waterdrop scene, 32/8/8 trajectories)"
.venv/bin/python -m rgns.data.generate scene=waterdrop num_trajectories=32 splits.valid=8 splits.test=8 \
  out_dir=datasets/waterdrop40_main
phase "dataset (generated, or found complete)"

# model, its steps and its time cap; the budgets come from docs/main_job.md's measurements
train() {
  local model=$1 steps=$2 cap=$3; shift 3
  # into a log file: progress lines (callbacks.time_split) instead of a progress bar redrawn every step
  .venv/bin/python train.py experiment=main model="$model" trainer.max_steps="$steps" trainer.max_time="$cap" \
    trainer.enable_progress_bar=false hydra.run.dir="$out/train/$model" "$@" > "$out/train/$model.log" 2>&1
}
echo "== 2/3 training -> $out/train (R-GNS, then Sep-GNS | GNS; logs: $out/train/<model>.log)"
# sizes and recipes per model: docs/main_job.md (equal message-passing steps: R-GNS's 2 blocks hold
# 4 couplings, GNS has 4 interaction layers; pushforward helped GNS, R-GNS needs the time for steps)
# (each step budget is a multiple of the validation interval, 2,500: the evaluated checkpoint is
# chosen at validations; with the pairwise options a step costs more: on an idle 2-core machine
# R-GNS ends its steps 5 s inside its cap and GNS's cap stops it near step 15,800
# (docs/main_job.md): the checkpoint is then chosen among the validations reached)
# (R-GNS without the memory-saving backward: plain autograd is 1.4x the steps/s at this size on a CPU;
# R-GNS and GNS compiled (module.compile): 1.4-2x their eager steps/s in this job after 1-2 min of
# compilation; Sep-GNS's short run stays eager; docs/main_job.md)
# (GNS has a core to itself: 20,000 steps, where 7,500 left it 1.25x the 0.1x bar; R-GNS's best
# checkpoint is often an early one, so it shares its core with Sep-GNS; caps sized for a 2-core
# machine that trains GNS 32x4 eager at about 20 steps/s per process; docs/main_job.md)
# (pair terms that cancel, momentum conserved away from the walls: R-GNS's couplings=pairwise and
# GNS's decoder=pairwise, with gravity as their reference; the three-seed study in docs/main_job.md)
( train rgns 12500 00:00:11:00 model.memory_saving=false module.compile=true model.couplings=pairwise "$@" \
  && train sep_gns 5000 00:00:04:00 model.layers=4 recipe=pushforward model.decoder=pairwise "$@" ) &
first=$!
train gns 20000 00:00:15:00 model.layers=4 recipe=pushforward module.compile=true model.decoder=pairwise "$@" &
second=$!
status=0
wait $first || status=$?
wait $second || status=$?
for model in rgns gns sep_gns; do
  [ -f "$out/train/$model.log" ] && grep -h "^\[time\]" "$out/train/$model.log" | sed "s/^/$model: /" || true
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
pretrained=$(ls pretrained/waterdrop40_main_64/{rgns,gns}.ckpt pretrained/waterdrop40_main/{rgns_forward_only,sep_gns}.ckpt \
  2>/dev/null | paste -sd, - || true)
.venv/bin/python evaluate.py checkpoints_dir="$out/train" checkpoint=best trajectories=8 workers=2 \
  'task.inverse.horizons=[1,5,20,40]' "pretrained=[$pretrained]" without_hard_walls=fresh \
  data_root=datasets/waterdrop40_main hydra.run.dir="$out/evaluation"
phase "evaluation"

ln -sfn "$(basename "$out")" outputs/main/latest
echo "Report: $out/evaluation/report.md (also outputs/main/latest/evaluation/report.md)"
echo "Time per phase: $timing"
echo "TensorBoard: .venv/bin/tensorboard --logdir $out/train"
