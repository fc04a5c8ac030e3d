#!/usr/bin/env python3
"""The distribution head of a bundle in plain numpy (OpenBLAS), timed on the same grid as
`alignist-train bench`, so the Rust head's throughput can be compared side by side.

Usage:
  target/release/alignist-train grid --level 4 --out /tmp/grid4.csv
  python3 benches/reference_head.py models/symsol1 /tmp/grid4.csv

It reads the bundle's `network.safetensors` by hand (8-byte header length, JSON header, raw
little-endian f32), builds the cube encoding of every grid rotation, precomputes the rotation
half of the first layer (as the engine does at load), and times the rest of the head for one
image feature: relu(img + rot) -> 2 branches x (3 hidden 256x256 ReLU layers + output).
"""
import json
import struct
import sys
import time

import numpy as np


def load_safetensors(path):
    raw = open(path, "rb").read()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8 : 8 + n])
    data = raw[8 + n :]
    out = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        assert info["dtype"] == "F32", (name, info["dtype"])
        start, end = info["data_offsets"]
        out[name] = np.frombuffer(data[start:end], dtype="<f4").reshape(info["shape"])
    return out


def quat_to_matrix(q):
    w, x, y, z = q.T
    return np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=1,
    ).reshape(-1, 3, 3)


def cube_encoding(m):
    vertices = np.array(
        [[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], dtype=np.float32
    )
    coords = np.einsum("nij,vj->nvi", m, vertices).reshape(len(m), 24)
    parts = []
    for k in range(3):
        f = 2.0**k
        parts += [np.sin(f * coords), np.cos(f * coords)]
    return np.concatenate(parts, axis=1).astype(np.float32)


def main():
    bundle, grid_csv = sys.argv[1], sys.argv[2]
    w = load_safetensors(f"{bundle}/network.safetensors")
    q = np.loadtxt(grid_csv, delimiter=",", skiprows=1)[:, 1:5]
    rot = cube_encoding(quat_to_matrix(q).astype(np.float32))
    rot_proj = rot @ w["head.rotation_proj.weight"] + w["head.rotation_proj.bias"]
    feature = np.random.default_rng(0).standard_normal(
        w["head.image_proj.weight"].shape[0], dtype=np.float32
    )
    img = feature @ w["head.image_proj.weight"] + w["head.image_proj.bias"]

    def branch(name, x):
        i = 0
        while f"head.{name}.hidden.{i}.weight" in w:
            x = np.maximum(x @ w[f"head.{name}.hidden.{i}.weight"] + w[f"head.{name}.hidden.{i}.bias"], 0)
            i += 1
        return (x @ w[f"head.{name}.output.weight"] + w[f"head.{name}.output.bias"])[:, 0], i

    def head():
        x = np.maximum(rot_proj + img, 0)
        s, layers = branch("shape_branch", x)
        f, _ = branch("feature_branch", x)
        return s + f, layers

    scores, layers = head()
    assert np.all(np.isfinite(scores))
    best = min(timeit(head) for _ in range(5))
    h = rot_proj.shape[1]
    flops = 2 * (layers * 2 * h * h + 2 * h)
    n = len(q)
    print(
        f"numpy head ({np.__version__}) on {n} rotations: {best * 1e3:.1f} ms, "
        f"{n / best / 1e6:.2f} M rotations/s, {n * flops / best / 1e9:.1f} GFLOP/s"
    )


def timeit(f):
    t = time.perf_counter()
    f()
    return time.perf_counter() - t


if __name__ == "__main__":
    main()
