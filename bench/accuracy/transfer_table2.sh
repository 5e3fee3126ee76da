#!/usr/bin/env bash
# Sim-to-real benchmark (docs/transfer.md): the paper's Table 2 on proxy-real, starting from the
# shipped model (or a checkpoint you pass). Prints the table and whether the targets are met
# (fine-tuned >= real-only + 10 top-view box mIoU; fine-tuned beats synthetic-only on every cell);
# writes chart.png and learning_curve.png. The architecture of all three regimes is the
# checkpoint's; real-only starts from the ImageNet encoder.
#   bench/accuracy/transfer_table2.sh [PRETRAINED_CKPT] [OUT_DIR]
# Env: SEEDS (default 1), FRACTIONS (default 1.0), MINUTES per run (default 6), EPOCHS (default 12).
# About 15 min on 2 cores with the defaults.
set -euo pipefail
CKPT=${1:-$(.venv/bin/python -c "from racklay.release import release_weights; print(release_weights())")}
OUT=${2:-outputs/transfer-bench}
REAL=${REAL:-/work/data/proxy_real}
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296
if [ ! -f "$REAL/splits/test.txt" ]; then
  .venv/bin/racklay synth --recipe proxy_real --n 542 --out "$REAL" --seed 1 --set layout_size=256 \
    --workers 2 --no-progress
fi

.venv/bin/transfer compare --pretrained "$CKPT" --real "$REAL" --out "$OUT" --seeds "${SEEDS:-1}" \
  --fractions "${FRACTIONS:-1.0}" --no-disc --batch-size 8 --epochs "${EPOCHS:-12}" --patience 4 \
  --max-minutes "${MINUTES:-6}"
cat "$OUT/table.md"
