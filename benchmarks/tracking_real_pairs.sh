#!/usr/bin/env bash
# tracking_real.py at several seeds for two variants, the two of a seed side by side (then the next seed), each
# scored for tracking (its tracking_real.md) and for where its gears went at the held-out camera (gear_masks.py): the
# defaults ("default") against a baseline ("baseline") trained with the ns-train options in $BASELINE_TRAIN and
# tracked with $BASELINE_TRACK.
#
#   BASELINE_TRAIN="--pipeline.gear-updates.static-views 0 --pipeline.model.gear-feature-dim 8
#     --pipeline.gear-updates.mask-source sam" \
#   BASELINE_TRACK="--min-views 2" bash benchmarks/tracking_real_pairs.sh OUTPUT "SEEDS" [tracking_real.py options]
#
# Each run's log, its tracking table and its gear shares go to OUTPUT/<variant>_s<seed>.txt. The capture's masks are
# <capture>_masks, scored at the held-out camera (--held-out; both must be among the tracking_real.py options).
set -uo pipefail
cd "$(dirname "$0")/.."
output=$1 seeds=$2
shift 2
options=("$@")
capture=$(python3 -c 'import sys; a = sys.argv[1:]; print(a[a.index("--capture") + 1])' "${options[@]}")
held_out=$(python3 -c 'import sys; a = sys.argv[1:]; print(a[a.index("--held-out") + 1])' "${options[@]}")
mkdir -p "$output"
one() {
  local variant=$1 seed=$2 run="$output/runs/$1_s$2" text="$output/$1_s$2.txt"
  shift 2
  python3 benchmarks/tracking_real.py "${options[@]}" --seed "$seed" --output "$run" "$@" >"$text" 2>&1
  python3 benchmarks/gear_masks.py "$run/runs/tracking/gear-nerf-small/run/config.yml" "${capture}_masks" \
    --cameras "$held_out" --held-out >>"$text" 2>&1
  grep -h "Gear update\|reviewed\|Gear updates end" "$run/runs/train.log" >>"$text"
  cat "$run/tracking_real.md" >>"$text"
}
for seed in $seeds; do
  one default "$seed" &
  one baseline "$seed" --train-options="${BASELINE_TRAIN:-}" ${BASELINE_TRACK:-} &
  wait
done
