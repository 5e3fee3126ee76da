#!/usr/bin/env bash
# Table 1 at paper scale on one CUDA GPU, within a fixed time budget: renders a paper-sized
# WareSynth `complex` set (N images, 90 % train / 10 % val, layouts at 512²) and trains two
# RackLay-D arms side by side on it for MINUTES each, the learning rate decaying over the budget
# (--schedule time):
#   A: the `light` decoder at 160x256 input -> 256² layouts (the project's CPU resolution)
#   B: the `light` decoder at 288x480 input -> 512² layouts (about the paper's resolution)
# so the same GPU time measures whether resolution or epochs close the gap to the paper's cells.
# Each arm's best weights come back as an fp16 release file in OUT; score them on the CPU with
#   racklay eval --weights OUT/A.safetensors --data /work/data/complex-test --native
# (the test set of bench/accuracy/release_targets.py: complex, seed 2027, 2,000 images, D = 512).
#   MINUTES=6 N=9000 WORK=/dev/shm/table1 OUT=runs/table1 bench/accuracy/table1_gpu.sh
# ARGS adds training flags to both arms (e.g. ARGS="--threads 2"). What limited the 2026-11-27
# lease (the training processes, not the GPU or the loader): docs/results/2026-11-27-ninth-session.md.
# A dry run on a CPU: DEVICE=cpu N=40 MINUTES=0.3 SYNTH_WORKERS=1 WORKERS=0 BATCH=4 bench/accuracy/table1_gpu.sh
set -euo pipefail
MINUTES=${MINUTES:-6}
N=${N:-9000}
WORK=${WORK:-/dev/shm/table1}
OUT=${OUT:-runs/table1}
DEVICE=${DEVICE:-cuda}
SYNTH_WORKERS=${SYNTH_WORKERS:-$(nproc)}
WORKERS=${WORKERS:-$(( ($(nproc) - 2) / 2 ))}   # DataLoader workers per arm
BATCH=${BATCH:-32}
ARGS=${ARGS:-}
PY=${PY:-python3}
mkdir -p "$OUT" "$WORK"
t0=$(date +%s)
$PY -m racklay synth --recipe complex --n "$N" --seed 11 --out "$WORK/complex" --workers "$SYNTH_WORKERS" \
  --set layout_size=512 --set 'splits={train: 0.9, val: 0.1, test: 0.0}' --set write_depth=false \
  --set write_normals=false --set write_semantic=false --set write_instance=false --set write_kitti=false \
  --set write_coco=false --no-progress
echo "synth: $N images in $(( $(date +%s) - t0 )) s"
COMMON="--data $WORK/complex --out $WORK/runs --decoder light --no-disc --augment paper --class-weights 1,5,10
  --batch-size $BATCH --lr 1e-3 --warmup-steps 200 --epochs 200 --schedule time --max-minutes $MINUTES
  --patience 0 --checkpoint-every 0 --no-cache --workers $WORKERS --device $DEVICE --seed 0 --no-progress $ARGS"
$PY -m racklay train $COMMON --name A --image-size 160x256 --layout-size 256 > "$OUT/A.log" 2>&1 &
a=$!
$PY -m racklay train $COMMON --name B --image-size 288x480 --layout-size 512 > "$OUT/B.log" 2>&1 &
b=$!
status=0
wait $a || status=$?
wait $b || status=$?
for arm in A B; do
  tail -n 3 "$OUT/$arm.log"
  cp "$WORK/runs/$arm/metrics.csv" "$OUT/$arm-metrics.csv" || true
  $PY -c "from racklay.release import make_release; make_release('$WORK/runs/$arm/best.safetensors', '$OUT/$arm.safetensors')" || status=1
done
echo "total $(( $(date +%s) - t0 )) s"
exit $status
