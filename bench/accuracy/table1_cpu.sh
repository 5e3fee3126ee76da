#!/usr/bin/env bash
# Table 1's reproduction row on a CPU, one session at a time: RackLay-D (the shipped Lite0 encoder,
# the `light` decoder, no discriminators) trained on a paper-sized WareSynth `complex` set
# (8,000 train / 2,000 val, seed 11, 256² layouts: the set of the GPU runs) for EPOCHS epochs.
#   bench/accuracy/table1_cpu.sh                 # render if missing, train or continue the run
#   kill <pid>   (or the session ends)           # any time: the run keeps last.safetensors
#   (SIGTERM; a background job ignores SIGINT: the shell sets it to ignored for `&` jobs)
#   bench/accuracy/table1_cpu.sh                 # next session: continues where it stopped
# ($RUNS and $DATA live on the machine: a session that comes up on a new machine starts over.)
# The learning rate follows one cosine over all EPOCHS, whatever the number of calls; a call that
# finds $RUNS/$NAME/last.safetensors resumes it (the same settings: the trainer refuses others).
# Score the best epoch so far against the paper's row on the `complex` test set of
# bench/accuracy/release_targets.py (seed 2027, D = 512; that script renders it if missing):
#   .venv/bin/python -c "from racklay.release import make_release; make_release('/work/runs/table1-light/best.safetensors', 'l.safetensors')"
#   .venv/bin/python -m racklay eval --weights l.safetensors --data /work/data/complex-test --split test --native --limit 400
# One 8,000-image epoch takes ~9 min on a 2-core Zen 4 in bf16 with nothing else running, validation included (the first fills the cache; sharing the cores doubles it).
# The GPU recipe (bench/accuracy/table1_gpu.sh) is the same but for the batch (16 here) and its time schedule.
set -euo pipefail
DATA=${DATA:-/work/data/complex8k}
RUNS=${RUNS:-/work/runs}
NAME=${NAME:-table1-light}
EPOCHS=${EPOCHS:-30}
PY=${PY:-.venv/bin/python}
if [ ! -f "$DATA/splits/val.txt" ]; then
  $PY -m racklay synth --recipe complex --n 10000 --seed 11 --out "$DATA" --workers "$(nproc)" \
    --set layout_size=256 --set 'splits={train: 0.8, val: 0.2, test: 0.0}' --set write_depth=false \
    --set write_normals=false --set write_semantic=false --set write_instance=false --set write_kitti=false \
    --set write_coco=false --no-progress
fi
RESUME=""
[ -f "$RUNS/$NAME/last.safetensors" ] && RESUME="--resume"
exec $PY -m racklay train --data "$DATA" --out "$RUNS" --name "$NAME" --decoder light --no-disc \
  --image-size 160x256 --layout-size 256 --augment paper --class-weights 1,5,10 --batch-size 16 --lr 1e-3 \
  --warmup-steps 200 --epochs "$EPOCHS" --patience 0 --checkpoint-every 100 --seed 0 --no-progress $RESUME
