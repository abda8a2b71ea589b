#!/usr/bin/env python3
"""force_ceiling: how much of a tpcloth dataset's forces any spring network could explain.

springtime fits per-spring stiffness to forces (paper Eqs. 7-10). This script asks, with the
simulator's own ground truth, whether that is possible at all on a tpcloth dataset:

1. frames: the share of the finite-difference accelerations (camera rate, no velocities) that
   tpcloth's own force model explains at the same states (are the frames fine enough?);
2. uniform: the share of the free vertices' true membrane forces that springs of one uniform
   stiffness explain (springs on the data mesh's own grid: structural, both shear diagonals,
   bending springs of stride 2, as springtime's default surrogate when nx = ny = res);
3. per spring: the same with every spring's stiffness free (unregularised least squares): the
   best any linear spring network of this topology could do;
4. the same two fits on random small perturbations of the flat sheet, where springs work.

Run on data written with --jitter 0 so that the grid is the mesh (no interpolation involved):

    python3 tpcloth.py /tmp/tpj0 --rollouts 2 --test 0 --seconds 1.5 --res 17 --fps 100 \\
        --young 200 600 2000 --edge-damping 0.15 --jitter 0
    python3 force_ceiling.py /tmp/tpj0
"""

import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import tpcloth as tp  # noqa: E402


def grid_springs(n, stride=2):
    """springtime's default spring set on an n x n grid (index j * n + i)."""
    out = []
    for j in range(n):
        for i in range(n):
            for di, dj in [(1, 0), (0, 1), (1, 1), (-1, 1), (stride, 0), (0, stride)]:
                if 0 <= i + di < n and 0 <= j + dj < n:
                    out.append((j * n + i, (j + dj) * n + i + di))
    return np.array(out)


def design(x, springs, rest_len):
    """Force per vertex of unit stiffness on each spring: [3V, S]."""
    d = x[springs[:, 1]] - x[springs[:, 0]]
    length = np.linalg.norm(d, axis=1, keepdims=True)
    fk = (length - rest_len[:, None]) * d / length
    out = np.zeros((len(x), 3, len(springs)))
    cols = np.arange(len(springs))
    for c in range(3):
        np.add.at(out[:, c, :], (springs[:, 0], cols), fk[:, c])
        np.add.at(out[:, c, :], (springs[:, 1], cols), -fk[:, c])
    return out.reshape(-1, len(springs))


def explained(states, cloth, springs, rest_len, rows):
    """Shares of the true membrane forces explained by uniform and per-spring stiffness."""
    s = len(springs)
    normal, rhs, yy = np.zeros((s, s)), np.zeros(s), 0.0
    for x in states:
        y = cloth.forces(x[None], np.zeros((1,) + x.shape), np.zeros(3))[0].ravel()[rows]
        a = design(x, springs, rest_len)[rows]
        normal += a.T @ a
        rhs += a.T @ y
        yy += y @ y
    one = np.ones(s)
    k_uniform = (one @ rhs) / (one @ normal @ one)
    uniform = 1 - (yy - 2 * k_uniform * (one @ rhs) + k_uniform**2 * (one @ normal @ one)) / yy
    k = np.linalg.lstsq(normal, rhs, rcond=None)[0]
    per_spring = 1 - (yy - 2 * k @ rhs + k @ normal @ k) / yy
    return uniform, per_spring


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="a tpcloth output folder (with tpcloth.json)")
    ap.add_argument("--rollout", default="train/rollout_000.npz")
    ap.add_argument("--every", type=int, default=5, help="use every n-th frame")
    a = ap.parse_args()
    meta = json.load(open(os.path.join(a.data, "tpcloth.json")))
    z = np.load(os.path.join(a.data, a.rollout), allow_pickle=True)
    rest, tris = z["rest_uv"], z["triangles"].astype(np.int64)
    x, dt, pinned = z["positions"], float(z["frame_dt"]), z["pinned"]
    young = z["tri_stiffness"].astype(np.float64)
    full = tp.Cloth(rest, tris, young, meta["poisson"], meta["density"], meta["bend"],
                    meta["edge_damping"], meta["drag"])
    membrane = tp.Cloth(rest, tris, young, meta["poisson"], meta["density"], 0.0, 0.0, 0.0)
    free = ~pinned
    gravity = np.asarray(z["gravity"], dtype=np.float64)

    v = (x[2:] - x[:-2]) / (2 * dt)
    acc = (x[2:] - 2 * x[1:-1] + x[:-2]) / dt**2
    model = full.forces(x[1:-1], v, gravity) / full.mass[None, :, None]
    res = np.sum((acc - model)[:, free] ** 2)
    print(f"frames: tpcloth's own forces explain {1 - res / np.sum(acc[:, free] ** 2):.3f} of the "
          f"finite-difference accelerations at {1 / dt:.0f} fps")

    n = meta["res"]
    if meta["jitter"] != 0 or len(rest) != n * n:
        sys.exit("force_ceiling: the spring fits need data written with --jitter 0")
    springs = grid_springs(n)
    rest_len = np.linalg.norm(rest[springs[:, 1]] - rest[springs[:, 0]], axis=1)
    rows = np.repeat(free, 3)
    frames = [x[f] for f in range(a.every, len(x), a.every)]
    u, p = explained(frames, membrane, springs, rest_len, rows)
    print(f"data states ({len(frames)} frames): uniform k explains {u:.3f}, per-spring k {p:.3f} "
          "of the free vertices' membrane forces")
    rng = np.random.default_rng(0)
    flat = np.concatenate([rest, np.zeros((len(rest), 1))], axis=1)
    noise = [flat + np.concatenate([rng.normal(0, 0.002, (len(rest), 2)),
                                    rng.normal(0, 0.01, (len(rest), 1))], axis=1)
             for _ in range(len(frames))]
    u, p = explained(noise, membrane, springs, rest_len, rows)
    print(f"perturbed flat sheet: uniform k explains {u:.3f}, per-spring k {p:.3f}")


if __name__ == "__main__":
    main()
