#!/usr/bin/env bash
# The SYMSOL-I experiment of docs/RESULTS.md, end to end on CPU:
#   train each shape's CAD experts (no symmetry is used: λ by the target width, mode tables from
#   the experts), then train, at one equal budget on fresh renders, Alignist (GKL, both experts,
#   mode-focused sampling, cube PE), the IPDF baseline, and the ablations GKL→L1,
#   mode-focused→random sampling and cube→IPDF encoding; evaluate each at grid level 3 on the same
#   fresh test renders (50 per shape, a seed no training uses), and print the tables.
# Usage: scripts/symsol_experiment.sh [WORK_DIR]   (default: target/symsol)
# Budget and sizes can be overridden with env vars (docs/RESULTS.md says which were used).
# Two trainings run at a time (JOBS).
set -euo pipefail
WORK=${1:-target/symsol}
SIZE=${SIZE:-32}
STEPS=${STEPS:-1500}
BATCH=${BATCH:-16}
K=${K:-256}
EVAL_LEVEL=${EVAL_LEVEL:-3}
EVAL_IMAGES=${EVAL_IMAGES:-50}
EVAL_SEED=${EVAL_SEED:-1099511627776}
JOBS=${JOBS:-2}
SHAPES=${SHAPES:-"tet cube icosa cone cyl"}
RUNS=${RUNS:-"alignist ipdf alignist-l1 alignist-random alignist-ipdfpe"}
cargo build --release --bin alignist-train
BIN=target/release/alignist-train
mkdir -p "$WORK/models" "$WORK/logs"
experts=()
for shape in $SHAPES; do
  if [ ! -f "$WORK/experts/$shape/manifest.json" ]; then
    "$BIN" experts --shape "$shape" --out "$WORK/experts/$shape"
  fi
  experts+=(--experts "$WORK/experts/$shape")
done
flags_of() {
  case "$1" in
    alignist) echo "--method alignist" ;;
    ipdf) echo "--method ipdf" ;;
    alignist-l1) echo "--method alignist --loss l1" ;;
    alignist-random) echo "--method alignist --sampling random" ;;
    alignist-ipdfpe) echo "--method alignist --encoding ipdf" ;;
    *) echo "unknown run $1" >&2; exit 2 ;;
  esac
}
running=0
for run in $RUNS; do
  out="$WORK/models/$run"
  if [ -f "$out/manifest.json" ]; then continue; fi
  # shellcheck disable=SC2046
  "$BIN" fit --fresh "${experts[@]}" $(flags_of "$run") --image-size "$SIZE" \
    --steps "$STEPS" --batch "$BATCH" --k "$K" --eval-level "$EVAL_LEVEL" \
    --eval-images "$EVAL_IMAGES" --eval-seed "$EVAL_SEED" --seed 0 --resume --profile \
    --out "$out" > "$WORK/logs/$run.log" 2>&1 &
  running=$((running + 1))
  if [ "$running" -ge "$JOBS" ]; then wait -n; running=$((running - 1)); fi
done
wait
models=()
for run in $RUNS; do models+=("$WORK/models/$run"); done
"$BIN" results "${models[@]}"
