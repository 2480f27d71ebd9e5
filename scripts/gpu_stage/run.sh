#!/bin/bash
# One call on a lent GPU machine (the device tool): the CUDA test, then eight
# fine-tuning runs side by side on the one GPU, each capped so that all have ended, checkpointed and
# been packed (optimiser state dropped, pack.py) into $OUT before DEADLINE_S seconds. Needs .gpu/
# from scripts/gpu_stage/prepare.sh; BENCH_S>0 runs `python -m rgns.bench models --device cuda` first.
# usage: bash scripts/gpu_stage/run.sh DEADLINE_S TRAIN_S [PYTHON]    (ACC=cpu to try it on a CPU)
set -u
DEADLINE=${1:-540}; TRAIN_S=${2:-400}; PY=${3:-python3}; ACC=${ACC:-gpu}
T0=$(date +%s); el() { echo $(( $(date +%s) - T0 )); }
OUT=${OUT:-/tmp/out}; mkdir -p $OUT
export TORCHINDUCTOR_COMPILE_THREADS=2 PYTHONPATH=$PWD/src:$PWD/.gpu/site PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 HYDRA_FULL_ERROR=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv 2>&1 | tail -2
$PY -c "import torch,lightning,torch_geometric,hydra,omegaconf,scipy,h5py;print('versions',torch.__version__,lightning.__version__,torch_geometric.__version__,hydra.__version__,'cuda',torch.cuda.is_available())"
$PY scripts/gpu_stage/codec.py unpack .gpu/data datasets/gpu128 .gpu/data/metadata.json > $OUT/unpack.log 2>&1 &
UNP=$!
if [ "$ACC" = gpu ] && [ "${BENCH_S:-0}" -gt 0 ]; then
  timeout ${BENCH_S:-0} $PY -m rgns.bench models --device cuda --repeats 10 --json $OUT/bench_models_cuda.json > $OUT/bench_models.log 2>&1
  echo "bench rc=$? t=$(el)"; tail -c 1500 $OUT/bench_models.log
fi
wait $UNP; echo "unpack rc=$? t=$(el)"; cat $OUT/unpack.log
mkdir -p outputs/gpu
R="experiment=main model=rgns model.memory_saving=false model.couplings=pairwise model.latent=128 model.galilean=true init_from=pretrained/waterdrop40_main_64/rgns.ckpt"
G="experiment=main model=gns model.layers=4 model.decoder=pairwise model.latent=64 model.galilean=true init_from=pretrained/waterdrop40_main_64/gns.ckpt"
S="recipe=unroll module.optimizer.lr=5e-5 module.scheduler.eta_min=2.5e-6 module.unroll.steps=[0] module.unroll.lengths=[6] data.horizon=6 trainer.max_steps=5000 data.root=datasets/gpu128 density_weight=10 trainer.val_check_interval=500 module.val_trajectories=8 trainer.enable_progress_bar=false +callbacks.checkpoint.save_top_k=-1 trainer.accelerator=$ACC trainer.log_every_n_steps=100"
P80="+module.pushforward={steps:[-1,-1,-1,-1],unrolls:[0,20,40,80],probs:[2,1,1,1]} data.lead=80"
P160="+module.pushforward={steps:[-1,-1,-1,-1],unrolls:[0,40,80,160],probs:[2,1,1,1]} data.lead=160 data.early_windows=true"
declare -A ARGS
ARGS[r80_s0]="$R $S $P80 seed=0"
ARGS[r80_s1]="$R $S $P80 seed=1"
ARGS[r80_s2]="$R $S $P80 seed=2"
ARGS[r80b8_s0]="$R $S $P80 seed=0 data.batch_size=8 module.optimizer.lr=1e-4 module.scheduler.eta_min=5e-6"
ARGS[r160e_s0]="$R $S $P160 seed=0"
ARGS[g80_s0]="$G $S $P80 seed=0"
ARGS[g80_s1]="$G $S $P80 seed=1"
ARGS[g80_s2]="$G $S $P80 seed=2"
declare -A PID COMPILE
start() {  # name compile
  local left=$(( DEADLINE - 25 - $(el) )); [ $left -gt $TRAIN_S ] && left=$TRAIN_S
  COMPILE[$1]=$2
  $PY train.py ${ARGS[$1]} module.compile=$2 trainer.max_time=$(printf "00:00:%02d:%02d" $((left/60)) $((left%60))) hydra.run.dir=outputs/gpu/$1 > outputs/gpu/$1.log 2>&1 &
  PID[$1]=$!; echo "start $1 compile=$2 max_time=${left}s t=$(el)"
}
for n in "${!ARGS[@]}"; do start $n true; done
if [ "$ACC" = gpu ]; then
  timeout 60 $PY -m pytest -q -p no:cacheprovider tests/test_models.py -k cuda > $OUT/pytest_cuda.log 2>&1; echo "pytest cuda rc=$? t=$(el)"; tail -3 $OUT/pytest_cuda.log
fi
while :; do
  alive=0
  for n in "${!PID[@]}"; do
    if kill -0 ${PID[$n]} 2>/dev/null; then alive=$((alive+1)); continue; fi
    wait ${PID[$n]}; rc=$?
    if [ $rc -ne 0 ] && [ "${COMPILE[$n]}" = true ] && [ $(el) -lt 300 ]; then
      echo "== $n died rc=$rc with compile, t=$(el):"; tail -5 outputs/gpu/$n.log; start $n false; alive=$((alive+1))
    else echo "end $n rc=$rc t=$(el)"; unset PID[$n]; fi
  done
  [ $alive -eq 0 ] && break
  if [ $(el) -ge $DEADLINE ]; then for n in "${!PID[@]}"; do kill -INT ${PID[$n]} 2>/dev/null; done; sleep 20; for n in "${!PID[@]}"; do kill -9 ${PID[$n]} 2>/dev/null; done; break; fi
  [ $(( $(el) % 60 )) -lt 5 ] && nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null | sed "s/^/gpu t=$(el): /"
  sleep 5
done
echo "trainings over t=$(el)"
for n in "${!ARGS[@]}"; do echo "$n: $(grep -h '\[time\]' outputs/gpu/$n.log | tail -1)"; grep -h '\[validation\]' outputs/gpu/$n.log | sed 's/val\/consistency_mse [^,]*, //' | tail -12; done
$PY scripts/gpu_stage/pack.py outputs/gpu $OUT
echo "packed t=$(el)"; ls -la $OUT
