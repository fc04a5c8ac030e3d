#!/usr/bin/env python3
"""The training step of `alignist-train bench --training` in PyTorch, for comparison only (the
project never depends on it): the same tiny ResNet encoder, cube encoding, dual-branch head,
losses and Adam, at the same batch, K and crop size, on the same CPU threads.

Usage: reference_training_step.py BATCH K IMAGE_SIZE STEPS WARMUP [profile]
Prints `ipdf step: X ms` and `alignist step: Y ms` (mean over STEPS after WARMUP); with `profile`,
the IPDF step's stages instead (encoder forward, head forward, loss, head backward, encoder
backward, optimiser), the encoder's backward run on its own from the features' gradient. Images are
random (no rendering) and the Alignist targets random log-weights (no experts): the step from
the images and targets on, which is what the network costs.
"""
import sys
import time

import torch
import torch.nn as nn
import torch.nn.functional as F


class ConvBn(nn.Module):
    def __init__(self, c_in, c_out, k, stride):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, stride, k // 2, bias=False)
        self.bn = nn.BatchNorm2d(c_out)

    def forward(self, x):
        return self.bn(self.conv(x))


class Block(nn.Module):
    def __init__(self, c_in, width, stride):
        super().__init__()
        self.a = ConvBn(c_in, width, 3, stride)
        self.b = ConvBn(width, width, 3, 1)
        self.shortcut = ConvBn(c_in, width, 1, stride) if stride != 1 or c_in != width else None

    def forward(self, x):
        identity = self.shortcut(x) if self.shortcut is not None else x
        return F.relu(self.b(F.relu(self.a(x))) + identity)


class Tiny(nn.Module):
    """`ResNetLayout::Tiny`: 3×3 stem, basic blocks [1, 1, 1, 1], widths 16 … 128."""

    def __init__(self):
        super().__init__()
        self.stem = ConvBn(3, 16, 3, 1)
        blocks, c = [], 16
        for stage in range(4):
            width = 16 << stage
            blocks.append(Block(c, width, 1 if stage == 0 else 2))
            c = width
        self.blocks = nn.Sequential(*blocks)

    def forward(self, x):
        h = self.blocks(F.relu(self.stem(x)))
        return h.mean(dim=(2, 3))


class Head(nn.Module):
    def __init__(self, image_dim=128, rotation_dim=144, hidden=256, layers=4):
        super().__init__()
        self.image_proj = nn.Linear(image_dim, hidden)
        self.rotation_proj = nn.Linear(rotation_dim, hidden)

        def branch():
            mods = []
            for _ in range(layers - 1):
                mods += [nn.Linear(hidden, hidden), nn.ReLU()]
            return nn.Sequential(*mods, nn.Linear(hidden, 1))

        self.shape, self.feature = branch(), branch()

    def forward(self, features, encodings):
        b, k, _ = encodings.shape
        x = F.relu(self.image_proj(features)[:, None, :] + self.rotation_proj(encodings))
        x = x.reshape(b * k, -1)
        return self.shape(x).reshape(b, k), self.feature(x).reshape(b, k)


VERTICES = torch.tensor(
    [[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)]
)


def cube_encoding(rotations):
    """`[n, 3, 3]` → `[n, 144]`: sin and cos of the rotated cube vertices at frequencies 1, 2, 4."""
    x = torch.einsum("nij,vj->nvi", rotations, VERTICES).reshape(-1, 24)
    return torch.cat([f(s * x) for s in (1.0, 2.0, 4.0) for f in (torch.sin, torch.cos)], dim=1)


def random_rotations(n):
    q, r = torch.linalg.qr(torch.randn(n, 3, 3))
    q = q * torch.sign(torch.diagonal(r, dim1=1, dim2=2))[:, None, :]
    return q * torch.sign(torch.linalg.det(q))[:, None, None]


def gkl(log_a, s):
    a = log_a.exp()
    return (a * (log_a - s) + s.exp() - a).sum(dim=1).mean()


def run(method, batch, k, size, steps, warmup):
    torch.manual_seed(0)
    encoder, head = Tiny(), Head()
    params = list(encoder.parameters()) + list(head.parameters())
    optim = torch.optim.Adam(params, lr=1e-4)
    times = []
    for step in range(warmup + steps):
        started = time.perf_counter()
        images = torch.rand(batch, 3, size, size)
        encodings = cube_encoding(random_rotations(batch * k)).reshape(batch, k, 144)
        shape, feature = head(encoder(images), encodings)
        if method == "ipdf":
            loss = -F.log_softmax(shape + feature, dim=1)[:, 0].mean()
        else:
            log_sdf = torch.randn(batch, k) - 3.0
            log_se = torch.randn(batch, k) - 3.0
            loss = gkl(log_sdf, shape) + gkl(log_se, feature)
        optim.zero_grad(set_to_none=True)
        loss.backward()
        optim.step()
        if step >= warmup:
            times.append(time.perf_counter() - started)
    return 1e3 * sum(times) / len(times)


def profile(batch, k, size, steps, warmup):
    """The IPDF step's stages, ms per step (mean over `steps` after `warmup`)."""
    torch.manual_seed(0)
    encoder, head = Tiny(), Head()
    optim = torch.optim.Adam(list(encoder.parameters()) + list(head.parameters()), lr=1e-4)
    totals = {}

    def timed(name, f):
        started = time.perf_counter()
        out = f()
        totals[name] = totals.get(name, 0.0) + time.perf_counter() - started
        return out

    for step in range(warmup + steps):
        if step == warmup:
            totals.clear()
        images = torch.rand(batch, 3, size, size)
        encodings = cube_encoding(random_rotations(batch * k)).reshape(batch, k, 144)
        features = timed("encoder forward", lambda: encoder(images))
        detached = features.detach().requires_grad_()
        shape, feature = timed("head forward", lambda: head(detached, encodings))
        loss = timed("loss", lambda: -F.log_softmax(shape + feature, dim=1)[:, 0].mean())
        optim.zero_grad(set_to_none=True)
        timed("head backward", loss.backward)
        timed("encoder backward", lambda: features.backward(detached.grad))
        timed("optimiser", optim.step)
    for name, seconds in totals.items():
        print(f"{name}: {1e3 * seconds / steps:.1f} ms")
    print(f"ipdf step (sum of the stages): {1e3 * sum(totals.values()) / steps:.1f} ms")


def main():
    batch, k, size, steps, warmup = (int(a) for a in sys.argv[1:6])
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    if sys.argv[6:] == ["profile"]:
        profile(batch, k, size, steps, warmup)
        return
    for method in ("ipdf", "alignist"):
        print(f"{method} step: {run(method, batch, k, size, steps, warmup):.1f} ms")


if __name__ == "__main__":
    main()
