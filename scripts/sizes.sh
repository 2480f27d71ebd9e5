#!/usr/bin/env bash
# The size sweep behind "model no more than a scene needs" (docs/benchmarks.md, `rgns.bench sizes`):
# one model at six sizes (latent x layers) from 16x1 to the shipped ones, seeds 0-2, each trained as
# the main job trains that model's base run (scripts/main.sh: experiment=main, its step budget and
# time cap, its model overrides), then all evaluated on their dataset's test split (task=forward:
# rollout MSE and ms per frame) and summarised by `python -m rgns.bench sizes`: per size the mean and
# spread over the seeds, and the smallest size within FACTOR of the best mean.
#
# Usage: bash scripts/sizes.sh [rgns|gns] [extra train.py overrides for every run]
# Environment (optional):
#   SIZES="16x1 32x1 32x2 64x2 128x2 64x4"  SEEDS="0 1 2"  JOBS=2 (trainings at once: main.sh's two)
#   STRIDES="1" the strides to train each size at (data.stride=k, the main job's validation rollout
#               of 150 frames and consistency of 20 as ceil(150/k) and ceil(20/k) steps; runs named
#               <size>_stride<k>_seed<seed>); all are scored on the frames every run predicts itself
#               (rollout_mse_shared, from frame 5 x the largest stride), sizes of their own per stride
#   STAGE=1     also each run's second stage, as main.sh does (experiment=main_stage from the base's
#               best checkpoint); the staged runs are evaluated beside the bases, as sizes of their own
#               (stride 1 only: the stage's push lengths are in frames)
#   FACTOR=1.5  EVALUATE="..." (extra evaluate.py overrides)  OUT=outputs/sizes/<model>/<time>
# Runs that fail are named at the end (their logs: <out>/train/<size>_seed<seed>.log); the others are
# still evaluated, and the script then exits 1.
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-rgns}
shift $(( $# > 0 ? 1 : 0 ))
case $model in  # scripts/main.sh's base run of the model (the sweep sets the size)
  rgns) steps=7500 cap=00:00:07:00 recipe=(model.memory_saving=false module.compile=true model.couplings=pairwise) ;;
  gns) steps=15000 cap=00:00:11:00 recipe=(module.compile=true model.decoder=pairwise recipe=pushforward) ;;
  *) echo "scripts/sizes.sh: the model is rgns or gns, not '$model'" >&2; exit 2 ;;
esac
read -r -a sizes <<< "${SIZES:-16x1 32x1 32x2 64x2 128x2 64x4}"
read -r -a seeds <<< "${SEEDS:-0 1 2}"
read -r -a strides <<< "${STRIDES:-1}"
for stride in "${strides[@]}"; do
  [[ $stride =~ ^[1-9][0-9]*$ ]] || { echo "scripts/sizes.sh: stride '$stride' is not a positive whole number" >&2; exit 2; }
  if [[ $stride != 1 && ${STAGE:-0} == 1 ]]; then
    echo "scripts/sizes.sh: STAGE=1 trains stride 1 only (the stage's push lengths are in frames), not stride $stride" >&2
    exit 2
  fi
done
read -r -a evaluate <<< "${EVALUATE:-}"
for size in "${sizes[@]}"; do
  [[ $size =~ ^[0-9]+x[0-9]+$ ]] || { echo "scripts/sizes.sh: size '$size' is not LATENTxLAYERS (e.g. 32x2)" >&2; exit 2; }
done
out=${OUT:-outputs/sizes/$model/$(date +%Y-%m-%d_%H-%M-%S)}
mkdir -p "$out/train"
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONWARNINGS=ignore

run_name() {  # run_name SIZE STRIDE SEED: <size>_seed<seed>, or <size>_stride<k>_seed<seed> at stride k > 1
  if [ "$2" = 1 ]; then echo "${1}_seed$3"; else echo "${1}_stride${2}_seed$3"; fi
}

train() {  # train SIZE STRIDE SEED [overrides]: the base run, then (STAGE=1) its second stage
  local size=$1 stride=$2 seed=$3; shift 3
  local run strided=()
  run="$out/train/$(run_name "$size" "$stride" "$seed")"
  if [ "$stride" != 1 ]; then
    strided=(data.stride="$stride" module.val_rollout_steps=$(( (150 + stride - 1) / stride ))
             module.val_consistency_steps=$(( (20 + stride - 1) / stride )))
  fi
  .venv/bin/python train.py experiment=main model="$model" model.latent="${size%x*}" model.layers="${size#*x}" \
    seed="$seed" trainer.max_steps="$steps" trainer.max_time="$cap" trainer.enable_progress_bar=false \
    "${recipe[@]}" "${strided[@]}" hydra.run.dir="$run" "$@" > "$run.log" 2>&1 || return 1
  [ "${STAGE:-0}" = 1 ] || return 0
  local best
  best=$(ls "$run"/checkpoints/best-step*.ckpt 2>/dev/null | head -n 1 || true)
  [ -n "$best" ] || { echo "no best-step*.ckpt in $run/checkpoints for the stage" >> "$run.log"; return 1; }
  .venv/bin/python train.py experiment=main_stage model="$model" model.latent="${size%x*}" model.layers="${size#*x}" \
    seed="$seed" trainer.max_steps=600 trainer.max_time=00:00:04:00 trainer.enable_progress_bar=false \
    "${recipe[@]}" init_from="$best" hydra.run.dir="${run}_stage" "$@" > "${run}_stage.log" 2>&1
}

echo "== 1/2 training ${#sizes[@]} sizes x ${#strides[@]} strides x ${#seeds[@]} seeds of $model, ${JOBS:-2} at a time -> $out/train"
declare -A running=()  # pid -> run name
failed=()
reap() {  # wait for one run to end and note it if it failed
  local pid status=0
  wait -n -p pid || status=$?
  [ "$status" -eq 0 ] || failed+=("${running[$pid]}")
  unset "running[$pid]"
}
for size in "${sizes[@]}"; do
  for stride in "${strides[@]}"; do
    for seed in "${seeds[@]}"; do
      while [ "${#running[@]}" -ge "${JOBS:-2}" ]; do reap; done
      train "$size" "$stride" "$seed" "$@" &
      running[$!]=$(run_name "$size" "$stride" "$seed")
    done
  done
done
while [ "${#running[@]}" -gt 0 ]; do reap; done

echo "== 2/2 evaluation -> $out/evaluation"
.venv/bin/python evaluate.py checkpoints_dir="$out/train" checkpoint=best task=forward trajectories=8 workers=2 \
  without_hard_walls=false references=null hydra.run.dir="$out/evaluation" "${evaluate[@]}"
.venv/bin/python -m rgns.bench sizes "$out/evaluation" --factor "${FACTOR:-1.5}" --metric rollout_mse_shared \
  --json "$out/sizes.json" \
  | tee "$out/sizes.md"
if [ "${#failed[@]}" -gt 0 ]; then
  echo "failed runs, left out above: ${failed[*]} (logs: $out/train/<run>.log)" >&2
  exit 1
fi
