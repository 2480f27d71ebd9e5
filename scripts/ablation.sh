#!/usr/bin/env bash
# The paper's ablations at the main job's budget (conf/paper.yaml's ablation figure; docs/paper.md):
# R-GNS as scripts/main.sh's base run trains it (32 x 2, pair couplings, 7,500 steps), once per
# variant and seed, two runs at a time (one thread each):
#   dl1 dl2 dl3 dl4    the loss designs (conf/loss; dl4 is the default)
#   ilp mlp            the invertible linear encoder/decoder (default) or an MLP
#   fixed updated      edge features fixed (default) or updated by each block
# The defaults' variants (dl4, ilp, fixed) are one and the same run: it is trained once, as dl4, and
# linked as ilp and fixed.
# Usage: bash scripts/ablation.sh [BENCHMARK] [seeds, default "0 1 2"] [extra train.py overrides]
#   runs go to outputs/ablation/<BENCHMARK>/<variant>/seed<N>/ (or $ABLATION_OUT/<variant>/seed<N>/), on
#   datasets/<BENCHMARK>40_main; a finished run (its folder's `done`) is skipped when run again, an
#   unfinished one starts again from scratch
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/lib.sh
benchmark=waterdrop
if [[ $# -gt 0 && $1 != *=* && ! $1 =~ ^[0-9\ ]+$ ]]; then benchmark=$1; shift; fi
check_benchmark scripts/ablation.sh "$benchmark"
seeds="0 1 2"
if [[ $# -gt 0 && $1 =~ ^[0-9\ ]+$ ]]; then seeds=$1; shift; fi
bash scripts/setup.sh
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONWARNINGS=ignore
data="datasets/${benchmark}40_main"
out=${ABLATION_OUT:-outputs/ablation/$benchmark}
mkdir -p "$out"
.venv/bin/python -m rgns.data.generate scene="$benchmark" num_trajectories=32 splits.valid=8 splits.test=8 \
  out_dir="$data"

# scripts/main.sh's R-GNS base run
rgns=(model=rgns model.memory_saving=false module.compile=true model.couplings=pairwise trainer.max_steps=7500)
declare -A variant=([dl1]=loss=dl1 [dl2]=loss=dl2 [dl3]=loss=dl3 [dl4]=loss=dl4 [mlp]=model.encoder=mlp
                    [updated]=model.edges=updated)
jobs=()
for seed in $seeds; do
  for name in dl1 dl2 dl3 dl4 mlp updated; do jobs+=("$seed $name"); done
done
run() {  # run SEED VARIANT
  local seed=$1 name=$2 dir="$out/$2/seed$1"
  [ -f "$dir/done" ] && return 0
  rm -rf "$dir" && mkdir -p "$dir"
  .venv/bin/python train.py experiment=main "${rgns[@]}" "${variant[$name]}" seed="$seed" trainer.max_time=null \
    trainer.enable_progress_bar=false data.root="$data" data.make_root="$data" data.make.scene="$benchmark" \
    hydra.run.dir="$dir" "${extra[@]}" > "$dir.log" 2>&1
  touch "$dir/done"
}
extra=("$@")
two_lanes run
for seed in $seeds; do  # the default run stands for every default variant
  for name in ilp fixed; do
    mkdir -p "$out/$name" && ln -sfn "../dl4/seed$seed" "$out/$name/seed$seed"
  done
done
echo "Ablation runs: $out/<variant>/seed<N>/ (bash scripts/paper.sh draws the figure)"
