#!/usr/bin/env bash
# Runs of `python -m benchmarks speed-accuracy` side by side on one lent GPU (several share it well), one (method, seed)
# each, into one output folder; then their records, logs and pictures packed into $OUT/runs.tgz.
#
#   bash benchmarks/gpu_seeds.sh SCENE ITERATIONS LIMIT_SECONDS METHOD:SEED [METHOD:SEED ...]
#
# There, carrying .device_site (benchmarks/gpu_env.sh pack). A run still going after LIMIT_SECONDS is stopped (its
# log comes back, its record does not), so that what finished comes back within the call's limit.
set -euo pipefail
cd "$(dirname "$0")/.."
bash benchmarks/gpu_env.sh setup
export PYTHONPATH=/tmp/site:/tmp/bench PATH=/tmp/site/bin:$PATH PYTHONUNBUFFERED=1
scene=$1 iterations=$2 limit=$3
shift 3
threads=$(($(nproc) / $#))
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader >/tmp/g_gpu.txt || true
for run in "$@"; do
  method=${run%%:*} seed=${run##*:}
  OMP_NUM_THREADS=$threads timeout "$limit" python3 -P -m benchmarks speed-accuracy --device cuda --output /tmp/g \
    --scenes "$scene" --main-methods "$method" --ablations --seeds 1 --first-seed "$seed" \
    --iterations "$iterations" --checkpoints 5 --eval-frames 6 >"/tmp/g_${method}_${seed}.log" 2>&1 &
done
wait || true
mkdir -p /tmp/g/logs && cp /tmp/g_*.log /tmp/g_gpu.txt /tmp/g/logs/
tar czf "$OUT/runs.tgz" -C /tmp/g --exclude='*.ckpt' --exclude='events.out.*' runs logs
tail -n 3 /tmp/g_*.log
