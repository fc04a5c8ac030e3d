#!/usr/bin/env bash
# Trains the shipped model models/symsol1 (one network for the five SYMSOL-I shapes) on fresh
# renders, the way the shipped bundle was made (its manifest records the fit command).
#   1. the experts of each shape (default settings; no symmetry is used), ~3 min each;
#   2. 16 000 steps of batch 16 × K 256 on 32 px crops, peak lr 1e-3 (~70 min on 2 cores),
#      resumable;
#   3. a warm restart from those weights: 12 000 more steps, peak lr 5e-4, another data seed
#      (~70 min with other work on the machine), resumable;
#   4. a second warm restart (data seed 2), run as it happened: 3 500 steps of a 12 000-step
#      schedule (peak lr 5e-4), stopped there (--stop-at), then resumed as a 7 000-step schedule
#      (the rest annealed to the floor in 3 500 steps, ~20 min);
#   5. a third warm restart (data seed 3): 10 000 steps, peak lr 3e-4 (~35 min);
#   6. a fourth warm restart (data seed 4): 10 000 steps, peak lr 2e-4 (~35 min alone; 68 min
#      beside other work);
#   7. four more warm restarts that draw fewer of the K rotations from the experts' mode table
#      (--focused-fraction; the paper's 3/4 until here), 5 000 steps each at peak lr 1e-4
#      (~19 min each): 1/2 (data seed 5), then 1/4 (seed 6), 1/10 (seed 7) and 1/20 (seed 8);
#   8. the bundle is evaluated on 250 fresh renders at level 3, then copied to models/symsol1.
# Usage: scripts/train_shipped_model.sh [WORK_DIR]   (default: target/symsol)
set -euo pipefail
cd "$(dirname "$0")/.."
WORK=${1:-target/symsol}
cargo build --release --bin alignist-train
BIN=./target/release/alignist-train
E=$WORK/experts
for shape in tet cube icosa cone cyl; do
  if [ ! -f "$E/$shape/manifest.json" ]; then
    "$BIN" experts --shape "$shape" --out "$E/$shape"
  fi
done
"$BIN" fit --fresh \
  --experts "$E/tet" --experts "$E/cube" --experts "$E/icosa" --experts "$E/cone" --experts "$E/cyl" \
  --method alignist --image-size 32 --steps 16000 --batch 16 --k 256 --lr 1e-3 \
  --eval-level 3 --eval-images 50 --checkpoint-every 500 --seed 0 --profile --resume \
  --out "$WORK/models/alignist-fresh"
"$BIN" fit --fresh \
  --experts "$E/tet" --experts "$E/cube" --experts "$E/icosa" --experts "$E/cone" --experts "$E/cyl" \
  --method alignist --image-size 32 --steps 12000 --batch 16 --k 256 --lr 5e-4 \
  --eval-level 3 --eval-images 50 --checkpoint-every 500 --seed 1 --profile --resume \
  --init "$WORK/models/alignist-fresh" \
  --out "$WORK/models/alignist-warm"
FIT_WARM=("$BIN" fit --fresh
  --experts "$E/tet" --experts "$E/cube" --experts "$E/icosa" --experts "$E/cone" --experts "$E/cyl"
  --method alignist --image-size 32 --batch 16 --k 256
  --eval-level 3 --eval-images 50 --checkpoint-every 500 --profile --resume)
"${FIT_WARM[@]}" --steps 12000 --lr 5e-4 --seed 2 --stop-at 3500 \
  --init "$WORK/models/alignist-warm" --out "$WORK/models/alignist-warm2"
"${FIT_WARM[@]}" --steps 7000 --lr 5e-4 --seed 2 \
  --init "$WORK/models/alignist-warm" --out "$WORK/models/alignist-warm2"
"${FIT_WARM[@]}" --steps 10000 --lr 3e-4 --seed 3 \
  --init "$WORK/models/alignist-warm2" --out "$WORK/models/alignist-warm3"
"${FIT_WARM[@]}" --steps 10000 --lr 2e-4 --seed 4 \
  --init "$WORK/models/alignist-warm3" --out "$WORK/models/alignist-warm4"
FOCUSED=("${FIT_WARM[@]}" --steps 5000 --lr 1e-4)
"${FOCUSED[@]}" --seed 5 --focused-fraction 0.5 \
  --init "$WORK/models/alignist-warm4" --out "$WORK/models/alignist-ff50"
"${FOCUSED[@]}" --seed 6 --focused-fraction 0.25 \
  --init "$WORK/models/alignist-ff50" --out "$WORK/models/alignist-ff50-25"
"${FOCUSED[@]}" --seed 7 --focused-fraction 0.1 \
  --init "$WORK/models/alignist-ff50-25" --out "$WORK/models/alignist-ff10"
"${FOCUSED[@]}" --seed 8 --focused-fraction 0.05 \
  --init "$WORK/models/alignist-ff10" --out "$WORK/models/alignist-ff05"
rm -rf models/symsol1
cp -r "$WORK/models/alignist-ff05" models/symsol1
