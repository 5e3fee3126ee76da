#!/usr/bin/env bash
# Accuracy benchmark (docs/accuracy.md): WareSynth complex set -> RackLay-D-disc with the light
# (default) and the paper decoder under the same time budget, trained side by side (one thread
# each, so both see the same contention) -> Table-1 layout on the held-out test split.
#   bench/accuracy/accuracy.sh [DATA_DIR] [MINUTES] [SIZE]
# Epochs per decoder (LIGHT_EPOCHS, PAPER_EPOCHS) are set so that each run's cosine schedule
# ends inside the time budget (the paper decoder's steps are slower); MINUTES stops a run anyway.
set -euo pipefail
DATA=${1:-/work/data/complex-2400}
MIN=${2:-50}
SIZE=${3:-128}
LIGHT_EPOCHS=${LIGHT_EPOCHS:-25}
PAPER_EPOCHS=${PAPER_EPOCHS:-12}
PY=${PY:-.venv/bin/racklay}
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296
if [ ! -f "$DATA/splits/test.txt" ]; then
  nice -n 10 $PY synth --recipe complex --n 2400 --out "$DATA" --seed 0 --workers 2 --set layout_size=256 \
    --set write_depth=false --set write_normals=false --set write_semantic=false --set write_instance=false \
    --set write_kitti=false --set write_coco=false --no-progress
fi
mkdir -p runs
for dec in light paper; do
  name=accuracy-default; epochs=$LIGHT_EPOCHS
  [ "$dec" = paper ] && name=accuracy-paper && epochs=$PAPER_EPOCHS
  nice -n 10 $PY train --data "$DATA" --out runs --name "$name" --decoder "$dec" --image-size "$SIZE" \
    --layout-size "$SIZE" --encoder resnet18 --amp auto --batch-size 8 --epochs "$epochs" --disc-start 5 --threads 1 \
    --max-minutes "$MIN" --patience 0 --checkpoint-every 50 > "runs/$name.log" 2>&1 &
done
wait
for name in accuracy-default accuracy-paper; do
  for mode in "" "--native"; do
    tag=${mode:+-native}
    nice -n 10 $PY eval --weights "runs/$name/best.safetensors" --data "$DATA" --split test --threads 2 $mode \
      --json "runs/$name/test$tag.json" | tee "runs/$name/test$tag.md"
  done
done
