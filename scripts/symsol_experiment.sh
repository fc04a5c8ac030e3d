#!/usr/bin/env bash
# The SYMSOL-I experiment of docs/RESULTS.md, end to end on CPU:
#   render the 5 shapes (train + test), train each shape's CAD experts, then train Alignist (GKL,
#   both experts, mode-focused sampling) and the IPDF baseline with the same encoder, data,
#   optimiser and budget, on the full training set and on 10 % of it, and evaluate at level 4.
# Usage: scripts/symsol_experiment.sh [WORK_DIR]   (default: target/symsol)
# Sizes can be overridden with env vars (defaults are what docs/RESULTS.md reports).
set -euo pipefail
WORK=${1:-target/symsol}
TRAIN_PER_SHAPE=${TRAIN_PER_SHAPE:-500}
TEST_PER_SHAPE=${TEST_PER_SHAPE:-6}
SIZE=${SIZE:-32}
STEPS=${STEPS:-1000}
BATCH=${BATCH:-16}
K=${K:-256}
EVAL_LEVEL=${EVAL_LEVEL:-4}
SHAPES=${SHAPES:-"tet cube icosa cone cyl"}
cargo build --release --bin alignist-train
BIN=target/release/alignist-train
mkdir -p "$WORK"
pairs=()
for shape in $SHAPES; do
  if [ ! -d "$WORK/data/$shape/test" ]; then
    "$BIN" render --shape "$shape" --count "$TRAIN_PER_SHAPE" --size "$SIZE" --seed 1 --out "$WORK/data/$shape"
    "$BIN" render --shape "$shape" --count "$TEST_PER_SHAPE" --size "$SIZE" --seed 2 --split test --out "$WORK/data/$shape"
  fi
  if [ ! -f "$WORK/experts/$shape/manifest.json" ]; then
    "$BIN" experts --shape "$shape" --out "$WORK/experts/$shape"
  fi
  pairs+=(--data "$WORK/data/$shape" --experts "$WORK/experts/$shape")
done
for fraction in 1.0 0.1; do
  for method in alignist ipdf; do
    out="$WORK/models/${method}-f${fraction}"
    if [ ! -f "$out/manifest.json" ]; then
      "$BIN" fit "${pairs[@]}" --method "$method" --fraction "$fraction" --image-size "$SIZE" \
        --steps "$STEPS" --batch "$BATCH" --k "$K" --eval-level "$EVAL_LEVEL" \
        --eval-images "$TEST_PER_SHAPE" --seed 0 --resume --out "$out"
    fi
  done
done
echo "bundles in $WORK/models; tables: target/release/alignist-train results $WORK/models/*"
