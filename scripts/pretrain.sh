#!/usr/bin/env bash
# The pretrained checkpoints in pretrained/waterdrop40_main/: the main job's models and recipes
# (experiment=main, scripts/main.sh's per-model overrides), trained long on one CPU core each, on
# the main job's dataset (R-GNS with pair couplings, GNS and Sep-GNS with the pairwise decoder, as
# scripts/main.sh). Each model's run folder goes to outputs/pretrain/<model>/; its checkpoint
# with the best validation rollout (8 validation trajectories, every 5,000 steps) is copied to
# pretrained/waterdrop40_main/<model>.ckpt with <model>.json: the command, the commit, the steps
# and the time it took. Models run side by side, one thread each (start at most one per core).
#
# Usage: bash scripts/pretrain.sh MODEL [MODEL ...] [-- OVERRIDES]   (rgns, rgns_forward_only, gns, sep_gns)
# (OVERRIDES go to every train.py run after the recipe's, e.g. for a smoke run with
#  PRETRAINED_DIR=/tmp/p bash scripts/pretrain.sh rgns -- trainer.max_steps=20 trainer.val_check_interval=10)
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -gt 0 ] || { echo "usage: bash scripts/pretrain.sh MODEL [MODEL ...] (rgns rgns_forward_only gns sep_gns)" >&2; exit 2; }
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONWARNINGS=ignore
models=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do models+=("$1"); shift; done
[ $# -gt 0 ] && shift  # the rest: overrides for every run
dest=${PRETRAINED_DIR:-pretrained/waterdrop40_main}
mkdir -p "$dest" outputs/pretrain

pretrain() {
  local model=$1 extra; shift
  case $model in  # step budgets sized for about an hour on one core beside another run (docs/pretrained.md)
    rgns) extra=(trainer.max_steps=60000 model.memory_saving=false module.compile=true model.couplings=pairwise) ;;
    rgns_forward_only) extra=(trainer.max_steps=60000 model.memory_saving=false module.compile=true) ;;
    gns|sep_gns) extra=(trainer.max_steps=70000 model.layers=4 recipe=pushforward module.compile=true model.decoder=pairwise) ;;
    *) echo "unknown model $model (rgns rgns_forward_only gns sep_gns)" >&2; return 2 ;;
  esac
  local run=outputs/pretrain/$model
  local args=(experiment=main model="$model" data.root=datasets/waterdrop40_main "${extra[@]}"
              trainer.max_time=00:01:20:00 trainer.val_check_interval=5000 module.val_trajectories=8
              trainer.enable_progress_bar=false hydra.run.dir="$run" "$@")
  local start=$SECONDS
  .venv/bin/python train.py "${args[@]}" > "$run.log" 2>&1
  local best
  best=$(ls "$run"/checkpoints/best-step*.ckpt | head -n 1)
  cp "$best" "$dest/$model.ckpt.partial" && mv "$dest/$model.ckpt.partial" "$dest/$model.ckpt"
  .venv/bin/python - "$dest/$model.json" "$best" "$((SECONDS - start))" "${args[@]}" <<'EOF'
import json, subprocess, sys
import torch
path, best, seconds, args = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4:]
checkpoint = torch.load(best, map_location="cpu", weights_only=False)
commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
json.dump({"command": "python train.py " + " ".join(args), "commit": commit, "checkpoint": best,
           "global_step": checkpoint["global_step"], "wall_s": seconds}, open(path, "w"), indent=2)
EOF
  echo "$model: $dest/$model.ckpt (from $best, $((SECONDS - start)) s)"
}

.venv/bin/python -m rgns.data.generate scene=waterdrop num_trajectories=32 splits.valid=8 splits.test=8 \
  out_dir=datasets/waterdrop40_main
pids=()
for model in "${models[@]}"; do pretrain "$model" "$@" & pids+=($!); done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=$?; done
exit $status
