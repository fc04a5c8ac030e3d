#!/usr/bin/env bash
# The SYMSOL-I experiment of docs/RESULTS.md, end to end on CPU:
#   train each shape's CAD experts (no symmetry is used: λ by the target width, mode tables from
#   the experts), then train, at one equal budget on fresh renders, Alignist (GKL, both experts,
#   mode-focused sampling, cube PE) and the IPDF baseline, on full data and on 10 % (a fixed pool
#   of a tenth of the images a run sees), the ablations GKL→L1, mode-focused→random sampling,
#   both experts→shape only / feature only, cube→IPDF encoding, and 32²→64² crops; evaluate each
#   at grid level 3 on the same fresh test renders (50 per shape, a seed no training uses), print
#   the tables and write them into docs/RESULTS.md (between its "tables" markers).
# Usage: scripts/symsol_experiment.sh [WORK_DIR]   (default: target/symsol)
# Budget and sizes can be overridden with env vars (docs/RESULTS.md says which were used).
# Two trainings run at a time (JOBS). Finished runs (a bundle with a manifest) are not redone;
# an interrupted one resumes from its checkpoints.
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
RUNS=${RUNS:-"alignist ipdf alignist-10pct ipdf-10pct alignist-l1 alignist-random alignist-shape alignist-feature alignist-ipdfpe alignist-64px"}
MODELS=${MODELS:-$WORK/experiment-$STEPS}
RESULTS=${RESULTS:-docs/RESULTS.md}
# BIN: a prebuilt alignist-train (e.g. a copy, so that rebuilding during a long run changes
# nothing); by default it is built here.
if [ -z "${BIN:-}" ]; then
  cargo build --release --bin alignist-train
  BIN=target/release/alignist-train
fi
mkdir -p "$MODELS/logs"
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
    alignist-10pct) echo "--method alignist --fraction 0.1" ;;
    ipdf-10pct) echo "--method ipdf --fraction 0.1" ;;
    alignist-shape) echo "--method alignist --fit-experts shape" ;;
    alignist-feature) echo "--method alignist --fit-experts feature" ;;
    alignist-64px) echo "--method alignist" ;;
    *) echo "unknown run $1" >&2; exit 2 ;;
  esac
}
size_of() {
  case "$1" in
    *-64px) echo 64 ;;
    *) echo "$SIZE" ;;
  esac
}
running=0
for run in $RUNS; do
  out="$MODELS/$run"
  if [ -f "$out/manifest.json" ]; then continue; fi
  # shellcheck disable=SC2046
  "$BIN" fit --fresh "${experts[@]}" --image-size "$(size_of "$run")" $(flags_of "$run") \
    --steps "$STEPS" --batch "$BATCH" --k "$K" --eval-level "$EVAL_LEVEL" \
    --eval-images "$EVAL_IMAGES" --eval-seed "$EVAL_SEED" --seed 0 --resume --profile \
    --out "$out" > "$MODELS/logs/$run.log" 2>&1 &
  running=$((running + 1))
  if [ "$running" -ge "$JOBS" ]; then wait -n; running=$((running - 1)); fi
done
wait
models=()
for run in $RUNS; do models+=("$MODELS/$run"); done
"$BIN" results "${models[@]}" > "$MODELS/tables.md"
cat "$MODELS/tables.md"
# The tables go into the results document between its markers, as they came out.
if grep -q '^<!-- tables -->$' "$RESULTS"; then
  awk -v tables="$MODELS/tables.md" '
    /^<!-- tables -->$/ { print; while ((getline line < tables) > 0) print line; skip = 1; next }
    /^<!-- \/tables -->$/ { skip = 0 }
    !skip { print }' "$RESULTS" > "$RESULTS.new"
  mv "$RESULTS.new" "$RESULTS"
  echo "tables written into $RESULTS"
fi
