"""The reference for `tests/net.rs`'s EfficientNet-Lite0 check: PyTorch's features of the fixed
64 px image of `examples/probe_efficientnet.rs` from the same weights file, in eval mode (running
statistics), globally averaged. PyTorch is used here only; the project never depends on it.

    python scripts/efficientnet_reference.py data/pretrained/efficientnet-lite0.pth
"""

import sys

import torch
import torch.nn.functional as F

from compare_pretrained import MEAN, STD, Lite0


def main():
    state = torch.load(sys.argv[1], map_location="cpu")
    model = Lite0(state, 1)
    missing, unexpected = model.load_state_dict(state, strict=False)
    assert set(missing) == {"cells.weight", "cells.bias"}, missing
    model.eval()
    s = 64
    c, y, x = torch.meshgrid(torch.arange(3), torch.arange(s), torch.arange(s), indexing="ij")
    image = (((c + 1) * (y * 7 + x * 3)) % 97).float().div(96.0).unsqueeze(0)
    with torch.no_grad():
        h = F.relu6(model._bn0(model._conv_stem((image - MEAN) / STD)))
        for b in model._blocks:
            h = b(h)
        f = F.relu6(model._bn1(model._conv_head(h))).mean((2, 3))[0]
    top = torch.topk(f, 6)
    print("top", [(i, round(v, 5)) for v, i in zip(top.values.tolist(), top.indices.tolist())],
          "at 100/200/300", [round(v, 5) for v in f[[100, 200, 300]].tolist()],
          "sum", round(f.sum().item(), 4), "zeros", int((f == 0).sum()))


if __name__ == "__main__":
    main()
