#!/usr/bin/env bash
# A WareSynth recipe A/B on a CPU, the renders-only protocol of the results log (sixth session on):
# per arm, render N scenes of RECIPE (seed SEED; the arm's own X_RECIPE and X_SETS), train the
# shipped architecture from ImageNet for EPOCHS epochs on 90 % of them, and score it with
# bench/accuracy/structure_ab.py on the test site of the labelled photos (REAL: `annotate export
# datasets/real-photos --out REAL --split-file datasets/real-photos/SOURCES.tsv`), calibrated on the
# other sites, and on all 131 photos. One arm at a time (2 cores: ~30 min per arm on a bf16 machine
# at the defaults); an arm whose score file exists is skipped and a half-trained arm resumes (`--resume`),
# so a stopped run picks up where it was.
# X_TRAIN: the arm's extra `racklay train` flags, after the protocol's (space-separated, e.g.
# gap5_TRAIN="--gap-weight 5": the same renders, another loss).
# X_SETS separates its `--set` keys with ';' (values may hold spaces). Example (the mixed_cover key
# groups, each added to `mixed` alone):
#   ARMS="tall packed" \
#   tall_SETS="rack_style={shelving: 0.59, pallet: 0.4, cube: 0.01};tall_view_fraction=0.05;tall_view_shelves=[8,14]" \
#   packed_SETS="flush_fraction=0.03;pallet_packing=0.1;pallet_gap=[0,0.15]" \
#   REAL=/tmp/real131s bench/accuracy/recipe_ab_cpu.sh
# Then compare: python -m bench.accuracy.structure_ab --arm tall=WORK/runs/tall --arm packed=... (same flags).
set -euo pipefail
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296   # racklay.runtime.MALLOC_ENV
RECIPE=${RECIPE:-mixed}
SEED=${SEED:-22}
N=${N:-2000}
EPOCHS=${EPOCHS:-10}
ARMS=${ARMS:-A B}
WORK=${WORK:-/work/recipe_ab}
REAL=${REAL:?REAL: a RackLay export of datasets/real-photos (see the header)}
THREADS=${THREADS:-2}
PY=${PY:-python3}
[ -f "$REAL/splits/test.txt" ] || { echo "$REAL: no splits/test.txt (export the photos with --split-file, see the header)"; exit 2; }
mkdir -p "$WORK/runs"
LEAN=(--set layout_size=256 --set "splits={train: 0.9, val: 0.1, test: 0.0}")
TRAIN=(--decoder struct --struct-fine --struct-gap --image-size 160x256 --layout-size 256 --no-letterbox --no-disc
  --augment paper --class-weights 1,5,10 --iou-weight 1 --batch-size 8 --threads "$THREADS"
  --checkpoint-every 0 --patience 0 --lr 1e-3 --warmup-steps 100 --epochs "$EPOCHS" --seed 0 --no-progress)
for arm in $ARMS; do
  score="$WORK/score-$arm.txt"
  if [ -f "$score" ]; then echo "arm $arm: scored already ($score)"; continue; fi
  rvar=${arm}_RECIPE
  svar=${arm}_SETS
  sets=()
  IFS=';' read -r -a kv <<< "${!svar:-}"
  for s in "${kv[@]}"; do [ -n "$s" ] && sets+=(--set "$s"); done
  tvar=${arm}_TRAIN
  read -r -a extra <<< "${!tvar:-}"
  echo "$(date -u +%T) arm $arm: render ${!rvar:-$RECIPE} ${sets[*]}"
  $PY -m racklay synth --recipe "${!rvar:-$RECIPE}" --n "$N" --seed "$SEED" --out "$WORK/data-$arm" \
    --workers "$THREADS" "${LEAN[@]}" "${sets[@]}" --no-progress | tail -n 1
  echo "$(date -u +%T) arm $arm: train ${extra[*]+${extra[*]}}"
  resume=()   # a stopped arm continues from its last finished epoch (--epochs stays the total)
  [ -f "$WORK/runs/$arm/last.safetensors" ] && resume=(--resume)
  $PY -m racklay train --data "$WORK/data-$arm" --out "$WORK/runs" --name "$arm" "${TRAIN[@]}" ${extra[@]+"${extra[@]}"} "${resume[@]}" | tail -n 3
  echo "$(date -u +%T) arm $arm: score"
  $PY -m bench.accuracy.structure_ab --arm "$arm=$WORK/runs/$arm" --data "$REAL" --split test \
    --photos datasets/real-photos --calibrate-on "$REAL:train" > "$score.part" 2>&1
  mv "$score.part" "$score"
  echo "$(date -u +%T) arm $arm: done ($score)"
done
