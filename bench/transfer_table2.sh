#!/usr/bin/env bash
# Sim-to-real benchmark (docs/transfer.md, "Recorded run 3"): the paper's Table 2 on proxy-real.
# Prints the table and whether the targets are met (fine-tuned >= real-only + 10 top-view box mIoU;
# fine-tuned beats synthetic-only on every cell); writes chart.png and learning_curve.png.
#   bench/transfer_table2.sh [PRETRAINED_CKPT] [OUT_DIR]
# PRETRAINED_CKPT: a synthetic model, by default bench/accuracy.sh's light run (about 50 min to
# make). Takes about 16 min on 2 cores (3 seeds x fractions 25 % / 100 %).
set -euo pipefail
CKPT=${1:-runs/accuracy-default/best.safetensors}
OUT=${2:-outputs/transfer-bench}
REAL=${REAL:-outputs/transfer-full/proxy_real}
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296
if [ ! -f "$CKPT" ]; then
  echo "$CKPT: no synthetic model; run bench/accuracy.sh first (or pass a checkpoint)" >&2
  exit 2
fi
if [ ! -f "$REAL/splits/test.txt" ]; then
  .venv/bin/racklay synth --recipe proxy_real --n 542 --out "$REAL" --seed 1 --set layout_size=128 \
    --workers 2 --no-progress
fi
.venv/bin/transfer compare --pretrained "$CKPT" --real "$REAL" --out "$OUT" --seeds 3 --fractions 0.25,1.0 \
  --image-size 128 --layout-size 128 --disc --batch-size 8 --epochs 12 --patience 5 --set amp=bf16
cat "$OUT/table.md"
