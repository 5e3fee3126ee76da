#!/usr/bin/env bash
# Table 1's reproduction row on a CPU, one session at a time: RackLay-D (the shipped Lite0 encoder,
# the `light` decoder, or with DECODER=struct the shipped model's; no discriminators) trained on a
# paper-sized WareSynth `complex` set (8,000 train / 2,000 val, seed 11, 256² layouts: the set of
# the GPU runs) for EPOCHS epochs, in the run $RUNS/table1-$DECODER.
#   bench/accuracy/table1_cpu.sh                 # render if missing, train or continue the run
#   kill <pid>   (or the session ends)           # any time: the run keeps last.safetensors
#   (SIGTERM to the script or to its `racklay train`; Ctrl-C in a terminal)
#   bench/accuracy/table1_cpu.sh                 # next session: continues where it stopped
# ($RUNS and $DATA live on the machine: a session that comes up on a new machine starts over.)
# The learning rate follows one cosine over all EPOCHS, whatever the number of calls; a call that
# finds $RUNS/$NAME/last.safetensors resumes it (the same settings: the trainer refuses others).
# When the last of the EPOCHS epochs is done, the script scores the best epoch against the paper's
# row on the first LIMIT (400) images of the `complex` test set of bench/accuracy/release_targets.py
# (seed 2027, D = 512; rendered if missing) and prints the Table 1 row. The best epoch so far,
# any time (SCORE_ONLY=1 skips training):
#   SCORE_ONLY=1 bench/accuracy/table1_cpu.sh
# One 8,000-image epoch takes ~9 min on a 2-core Zen 4 in bf16 with nothing else running, validation included (the first fills the cache; sharing the cores doubles it).
# FLAGS adds racklay train options to the recipe (an arm: e.g. FLAGS=--struct-back NAME=table1-struct-back
# with DECODER=struct); a resumed run must be given the same FLAGS (the trainer refuses others).
# RECIPE=complex_paper trains and scores on the WareSynth recipe with the paper authors' box placement
# (items centred on the shelf's depth, fixed sizes: docs/waresynth.md) in its own data folder
# (/work/data/complex_paper8k), run (table1-complex_paper-$DECODER) and test set (/work/data/complex_paper-test);
# RECIPE=complex_paper_fixed adds the authors' fixed rack size and camera (docs/waresynth.md), likewise.
# LAYOUT=512 trains on labels at the paper's (and the test set's) 512² instead of 256² (its own data folder,
# ${RECIPE}8k-512, 22 GB; samples not cached in memory; ~14 min an epoch): at 256² a pixel is 31 mm, and
# a model scored at 512² draws the 256² rounding (on complex_paper_fixed every shelf 2 rows too deep,
# docs/results/2026-12-07-sixty-second-session.md). With DECODER=struct, FLAGS="--init <a 256² run's best>"
# fine-tunes a model trained at 256² (a struct model's tensors do not depend on the layout size).
# The GPU recipe (bench/accuracy/table1_gpu.sh) is the same but for the batch (16 here) and its time schedule.
set -euo pipefail
RECIPE=${RECIPE:-complex}
if [ "$RECIPE" = complex ]; then TAG=""; else TAG="$RECIPE-"; fi
LAYOUT=${LAYOUT:-256}
if [ "$LAYOUT" = 256 ]; then SUFFIX=""; CACHE=""; else SUFFIX="-$LAYOUT"; CACHE="--no-cache"; fi
DATA=${DATA:-/work/data/${RECIPE}8k$SUFFIX}
TEST=${TEST:-/work/data/${RECIPE}-test}
RUNS=${RUNS:-/work/runs}
DECODER=${DECODER:-light}
NAME=${NAME:-table1-$TAG$DECODER}
EPOCHS=${EPOCHS:-30}
FLAGS=${FLAGS:-}
PY=${PY:-.venv/bin/python}
if [ ! -f "$DATA/splits/val.txt" ]; then
  $PY -m racklay synth --recipe "$RECIPE" --n 10000 --seed 11 --out "$DATA" --workers "$(nproc)" \
    --set "layout_size=$LAYOUT" --set 'splits={train: 0.8, val: 0.2, test: 0.0}' --set write_depth=false \
    --set write_normals=false --set write_semantic=false --set write_instance=false --set write_kitti=false \
    --set write_coco=false --no-progress
fi
LIMIT=${LIMIT:-400}
score() {
  $PY -m bench.accuracy.release_targets --weights "$RUNS/$NAME/best.safetensors" --limit "$LIMIT" \
    --complex "$TEST" --complex-recipe "$RECIPE" --proxy-real '' --real-photos ''
}
if [ -n "${SCORE_ONLY:-}" ]; then score; exit; fi
RESUME=""
[ -f "$RUNS/$NAME/last.safetensors" ] && RESUME="--resume"
$PY -m racklay train --data "$DATA" --out "$RUNS" --name "$NAME" --decoder "$DECODER" --no-disc \
  --image-size 160x256 --layout-size "$LAYOUT" --augment paper --class-weights 1,5,10 --batch-size 16 --lr 1e-3 \
  --warmup-steps 200 --epochs "$EPOCHS" --patience 0 --checkpoint-every 100 --seed 0 --no-progress $CACHE $RESUME $FLAGS &
train=$!
# `kill <this script's pid>` (or Ctrl-C) stops the training (SIGTERM: it exits 143 and keeps its last
# checkpoint, written every 100 steps) and the script exits with the trainer's status, unscored
trap 'kill -TERM "$train" 2>/dev/null' TERM INT
rc=0; wait "$train" || rc=$?
if kill -0 "$train" 2>/dev/null; then rc=0; wait "$train" || rc=$?; fi   # the first wait ended at the signal
[ "$rc" -eq 0 ] || exit "$rc"
# score only when every planned epoch is in metrics.csv
done_epochs=$(( $(wc -l < "$RUNS/$NAME/metrics.csv") - 1 ))
if [ "$done_epochs" -ge "$(sed -n 's/^epochs: //p' "$RUNS/$NAME/config.yaml")" ]; then score; fi
