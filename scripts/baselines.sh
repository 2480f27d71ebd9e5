#!/usr/bin/env bash
# The full forward comparison (docs/models.md, docs/main_job.md): GNS, EGNN, NeuralSPH and DMCF with
# GNS's budget and recipe in the main preset (experiment=main, 32 wide, 4 layers, pushforward,
# 10,000 steps), R-GNS with the main job's (15,000 steps), each over SEEDS, two runs at a time (one
# thread each), then one evaluation of all of them on the 8 test trajectories with the
# yardsticks, aggregated over seeds ("Over seeds" in the report).
# Usage: bash scripts/baselines.sh [BENCHMARK] [seeds, default "0 1 2"]
#   BENCHMARK: waterdrop (default; outputs/baselines/<time>/) or another training scene of conf/scene
#   (outputs/baselines_<BENCHMARK>/<time>/), on datasets/<BENCHMARK>40_main as scripts/main.sh makes it.
#   R-GNS-dagger (model=rgns_forward_only) trains with R-GNS's budget. conf/paper.yaml reads these runs.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/lib.sh
benchmark=waterdrop
if [[ $# -gt 0 && ! $1 =~ ^[0-9\ ]+$ ]]; then benchmark=$1; shift; fi
check_benchmark scripts/baselines.sh "$benchmark"
bash scripts/setup.sh
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONWARNINGS=ignore
seeds=${1:-"0 1 2"}
data="datasets/${benchmark}40_main"
if [[ $benchmark == waterdrop ]]; then runs=outputs/baselines; else runs="outputs/baselines_$benchmark"; fi
out="$runs/$(date +%Y-%m-%d_%H-%M-%S)"
mkdir -p "$out"
.venv/bin/python -m rgns.data.generate scene="$benchmark" num_trajectories=32 splits.valid=8 splits.test=8 \
  out_dir="$data"

jobs=()
for seed in $seeds; do
  jobs+=("$seed rgns trainer.max_steps=15000 model.memory_saving=false")
  jobs+=("$seed rgns_forward_only trainer.max_steps=15000 model.memory_saving=false")
  for model in gns egnn neural_sph dmcf; do
    jobs+=("$seed $model trainer.max_steps=10000 model.layers=4 recipe=pushforward")
  done
done
run() {  # run SEED MODEL OVERRIDES...
  local seed=$1 model=$2; shift 2
  .venv/bin/python train.py experiment=main model="$model" seed="$seed" "$@" trainer.max_time=null \
    trainer.enable_progress_bar=false data.root="$data" data.make_root="$data" data.make.scene="$benchmark" hydra.run.dir="$out/train/s$seed/$model" > "$out/s$seed.$model.log" 2>&1
}
two_lanes run

.venv/bin/python evaluate.py checkpoints_dir="$out/train" checkpoint=best trajectories=8 task=forward \
  data_root="$data" hydra.run.dir="$out/evaluation"
echo "Report: $out/evaluation/report.md"
