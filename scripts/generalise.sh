#!/usr/bin/env bash
# Where methods fail, across benchmarks (docs/generalise.md): every run of the main job's R-GNS, GNS and
# Sep-GNS on each benchmark rolled out on conditions it never saw, 1,000 steps forward (and backwards on
# the training scene), beside the training-free baselines and the dataset's solver at a coarser grid.
#
#   bash scripts/generalise.sh [key=value ...]                 # conf/paper.yaml's `generalise` section, Hydra overrides
#   bash scripts/generalise.sh generalise.only=[waterdrop]     # one benchmark
#   bash scripts/generalise.sh generalise.set=shipped          # the long-trained files instead of the main job's runs
#
# Every evaluation is cached (outputs/paper/cache): a rerun evaluates only what is new, a stopped run goes on.
# Writes outputs/paper/generalise/generalise.md, generalise.json and generalise.png.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/lib.sh
python_module rgns.failures "$@"
