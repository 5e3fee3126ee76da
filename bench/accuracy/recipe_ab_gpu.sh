#!/usr/bin/env bash
# A WareSynth recipe A/B at GPU scale, in one lease-sized call: renders the same scenes once per
# arm (RECIPE, seed SEED, N images each; arm A with A_SETS, arm B with B_SETS as extra `--set` keys;
# more arms with ARMS="A B C" and C_SETS=...; an arm of another recipe with e.g. B_RECIPE=release),
# then trains one renders-only model per arm side by side from ImageNet (the shipped architecture:
# struct decoder with the 1/4 detail branch and the gap output), the learning rate decaying over
# the time left (--schedule time). Everything is timed against one DEADLINE (seconds after the
# start), so the call always ends with every arm's best weights written as fp16 release files in
# OUT, whatever the rendering took. Score them on the CPU, e.g.
#   python -m bench.accuracy.structure_ab --arm A=OUT/A.safetensors --arm B=OUT/B.safetensors \
#     --data REAL --split test --photos datasets/real-photos --calibrate-on REAL:train
# Example (the 2026-11-27 lease: v8's packed `mixed` against the same plus the labels' visibility
# rule and long lenses):
#   A_SETS="pallet_packing=0.8 pallet_gap=[0.03,0.15]" \
#   B_SETS="pallet_packing=0.8 pallet_gap=[0.03,0.15] visible_fraction_board=0.2 focal_px=[200,2000] camera_distance=[0.35,15]" \
#   N=6000 DEADLINE=530 OUT=$OUT bench/accuracy/recipe_ab_gpu.sh   (68 s of rendering, 7 min of training per arm)
# Three arms (the open questions of 2026-11-28: `mixed`, with ambient occlusion, with its layouts
# continued across uprights):
#   ARMS="A B C" A_SETS="" B_SETS="ambient_occlusion=[0.5,3]" C_SETS="layout_extent=row" \
#   N=6000 DEADLINE=540 OUT=$OUT bench/accuracy/recipe_ab_gpu.sh
# Recipes against each other (the rack-styles issue's A/B: the coverage recipe, the training recipe, `release`):
#   ARMS="A B C" A_RECIPE=mixed_wide B_RECIPE=mixed C_RECIPE=release N=6000 DEADLINE=540 OUT=$OUT bench/accuracy/recipe_ab_gpu.sh
# A dry run on a CPU: DEVICE=cpu N=24 DEADLINE=150 SYNTH_WORKERS=1 WORKERS=0 BATCH=4 THREADS=1 bench/accuracy/recipe_ab_gpu.sh
set -uo pipefail
RECIPE=${RECIPE:-mixed}
SEED=${SEED:-11}
N=${N:-6000}
ARMS=${ARMS:-A B}
A_SETS=${A_SETS:-}
B_SETS=${B_SETS:-}
DEADLINE=${DEADLINE:-540}          # seconds from the start by which both arms have stopped training
MARGIN=${MARGIN:-45}               # kept for the data check before the first step and the release files
WORK=${WORK:-/dev/shm/recipe_ab}
OUT=${OUT:-runs/recipe_ab}
DEVICE=${DEVICE:-cuda}
n_arms=$(wc -w <<< "$ARMS")
SYNTH_WORKERS=${SYNTH_WORKERS:-$(( $(nproc) / n_arms ))}        # per arm; the renders run side by side
WORKERS=${WORKERS:-$(( ($(nproc) - 2 * n_arms) / n_arms ))}     # DataLoader workers per arm
THREADS=${THREADS:-2}                                  # torch host threads per training process
BATCH=${BATCH:-32}
ARGS=${ARGS:-}
PY=${PY:-python3}
mkdir -p "$OUT" "$WORK"
t0=$(date +%s)
elapsed() { echo $(( $(date +%s) - t0 )); }

sets() { local s; for s in $1; do printf -- "--set %s " "$s"; done; }
LEAN=(--set layout_size=256 --set "splits={train: 0.95, val: 0.05, test: 0.0}" --set write_depth=false
  --set write_normals=false --set write_semantic=false --set write_instance=false --set write_kitti=false
  --set write_coco=false)
declare -A pid
for arm in $ARMS; do
  var=${arm}_SETS
  rvar=${arm}_RECIPE
  # shellcheck disable=SC2046
  $PY -m racklay synth --recipe "${!rvar:-$RECIPE}" --n "$N" --seed "$SEED" --out "$WORK/$arm" --workers "$SYNTH_WORKERS" \
    "${LEAN[@]}" $(sets "${!var:-}") --no-progress > "$OUT/$arm.log" 2>&1 &
  pid[$arm]=$!
done
for arm in $ARMS; do
  wait "${pid[$arm]}" || { echo "arm $arm: synth failed"; tail -n 5 "$OUT/$arm.log"; exit 1; }
done
echo "synth: $n_arms x $N images in $(elapsed) s"
for arm in $ARMS; do tail -n 1 "$OUT/$arm.log"; done

left=$(( DEADLINE - $(elapsed) ))
minutes=$(awk "BEGIN {printf \"%.2f\", ($left - $MARGIN) / 60}")
echo "training budget: $minutes min per arm (hard stop in $left s)"
if command -v nvidia-smi > /dev/null; then
  nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 20 > "$OUT/gpu.csv" 2>&1 &
  smi=$!
fi
COMMON="--out $WORK/runs --decoder struct --struct-fine --struct-gap --image-size 160x256 --layout-size 256
  --no-letterbox --no-disc --augment paper --class-weights 1,5,10 --iou-weight 1 --batch-size $BATCH --lr 1e-3
  --warmup-steps 200 --epochs 200 --schedule time --max-minutes $minutes --patience 0 --checkpoint-every 0 --no-cache
  --workers $WORKERS --threads $THREADS --device $DEVICE --seed 0 --no-progress $ARGS"
for arm in $ARMS; do
  timeout --signal=INT --kill-after=10 "$left" $PY -m racklay train --data "$WORK/$arm" --name "$arm" $COMMON \
    >> "$OUT/$arm.log" 2>&1 &
  pid[$arm]=$!
done
status=0
for arm in $ARMS; do
  # 124 / 137: the hard stop at the deadline interrupted (or, past the 10 s grace, killed) a trainer
  # that --max-minutes had not yet stopped; its best weights so far are on disk and are used
  wait "${pid[$arm]}" || { rc=$?
    if [ "$rc" -eq 124 -o "$rc" -eq 137 ] && [ -f "$WORK/runs/$arm/best.safetensors" ]; then
      echo "arm $arm: stopped at the deadline (exit $rc); its best weights so far are used"
    else status=$rc; fi; }
done
[ -n "${smi:-}" ] && kill "$smi" 2> /dev/null
for arm in $ARMS; do
  tail -n 2 "$OUT/$arm.log"
  cp "$WORK/runs/$arm/metrics.csv" "$OUT/$arm-metrics.csv" || status=1
  $PY -c "from racklay.release import make_release; make_release('$WORK/runs/$arm/best.safetensors', '$OUT/$arm.safetensors')" \
    || status=1
done
echo "total $(elapsed) s"
exit $status
