#!/usr/bin/env bash
# The paper's tables across benchmarks from checkpoints (docs/paper.md):
#
#   bash scripts/paper.sh [key=value ...]           # conf/paper.yaml's manifest, Hydra overrides
#   bash scripts/paper.sh evaluate.trajectories=2   # fewer test trajectories (quicker; say so beside the numbers)
#   bash scripts/paper.sh refresh=true              # evaluate again, ignoring the cache
#
# Evaluates every checkpoint the manifest's globs find (each cached by its content, the dataset's
# and the settings: a rerun evaluates only what is new), the yardsticks and the optimisers once per
# benchmark, and writes outputs/paper/tables.md (Tables 1-3, the ablations), paper.json (every
# number) and the charts. One thread per process unless OMP_NUM_THREADS says.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/lib.sh
python_module rgns.paper "$@"
