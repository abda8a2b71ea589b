#!/usr/bin/env python3
"""spring_fit: can the forces of a tpcloth dataset identify a per-spring stiffness map at all?

The teacher-forced question under springtime's training: fit every spring's stiffness by linear
least squares to the data's own finite-difference accelerations (central second differences of
positions, camera rate, no stored velocities), `m (a - g) ~ sum_s k_s (|d_s| - l0_s) d_s/|d_s|`
over the free vertices of every stored frame, and rank the fitted k against the simulator's
Young's-modulus map (Spearman). Two spring networks:

- `--grid 0` (default): springs on the data mesh's own edges, the vertices' true masses: no
  resampling at all;
- `--grid N`: springtime's N x N surrogate grid (structural, both shear diagonals, stride-2
  bending), particles resampled from the landmarks piecewise-linearly in the data's triangles,
  equal particle masses, the structural springs ranked against the map at their midpoints.

    python3 spring_fit.py DATA/train            # the data's mesh
    python3 spring_fit.py DATA/train --grid 25  # a 25 x 25 surrogate grid over it
"""

import argparse
import glob
import os

import numpy as np


def rank(x):
    return np.argsort(np.argsort(x))


def spearman(a, b):
    return float(np.corrcoef(rank(a), rank(b))[0, 1])


def locate(uv, tris, p):
    """The triangle holding p (largest smallest barycentric weight) and p's weights in it."""
    a, b, c = uv[tris[:, 0]], uv[tris[:, 1]], uv[tris[:, 2]]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    wb = ((p[0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (p[1] - a[:, 1])) / det
    wc = ((b[:, 0] - a[:, 0]) * (p[1] - a[:, 1]) - (p[0] - a[:, 0]) * (b[:, 1] - a[:, 1])) / det
    wa = 1 - wb - wc
    t = int(np.argmax(np.minimum(np.minimum(wa, wb), wc)))
    return t, np.array([wa[t], wb[t], wc[t]])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="a folder of tpcloth rollouts (train/)")
    ap.add_argument("--grid", type=int, default=0, help="surrogate grid side (0: the data's mesh edges)")
    ap.add_argument("--every", type=int, default=3, help="use every n-th frame")
    a = ap.parse_args()
    files = sorted(glob.glob(os.path.join(a.data, "*.npz")))
    z = np.load(files[0], allow_pickle=True)
    uv, tris = z["rest_uv"], z["triangles"].astype(np.int64)
    young = z["tri_stiffness"].astype(np.float64)
    dt, width = float(z["frame_dt"]), float(z["width"])
    gravity = np.asarray(z["gravity"], dtype=np.float64)
    if a.grid:
        n = a.grid
        g = np.linspace(0.0, width, n)
        points = np.stack(np.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2)
        found = [locate(uv, tris, p) for p in points]
        index = np.array([tris[t] for t, _ in found])
        weight = np.array([w for _, w in found])
        springs, family = [], []
        for j in range(n):
            for i in range(n):
                for di, dj, f in [(1, 0, 0), (0, 1, 0), (1, 1, 1), (-1, 1, 1), (2, 0, 2), (0, 2, 2)]:
                    if 0 <= i + di < n and 0 <= j + dj < n:
                        springs.append((j * n + i, (j + dj) * n + i + di))
                        family.append(f)
        springs, family = np.array(springs), np.array(family)
        mass = np.full(len(points), float(z["total_mass"]) / len(points))
        mid = 0.5 * (points[springs[:, 0]] + points[springs[:, 1]])
        truth = np.array([young[locate(uv, tris, p)[0]] for p in mid])
        ranked = family == 0
    else:
        points, index, weight = uv, None, None
        e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
        springs = np.unique(np.sort(e, axis=1), axis=0)
        mass = z["vertex_mass"].astype(np.float64)
        per_edge = {}
        for t, tri in enumerate(tris):
            for u, v in [(0, 1), (1, 2), (2, 0)]:
                per_edge.setdefault(tuple(sorted((tri[u], tri[v]))), []).append(young[t])
        truth = np.array([np.mean(per_edge[tuple(s)]) for s in springs])
        ranked = np.ones(len(springs), bool)
    s_count, v_count = len(springs), len(points)
    rest = np.linalg.norm(points[springs[:, 1]] - points[springs[:, 0]], axis=1)
    incident = [[] for _ in range(v_count)]
    for s, (p, q) in enumerate(springs):
        incident[p].append((s, 1.0))
        incident[q].append((s, -1.0))
    width_k = max(len(x) for x in incident)
    inc_s, inc_sign = np.zeros((v_count, width_k), np.int64), np.zeros((v_count, width_k))
    for p, row in enumerate(incident):
        for c, (s, sign) in enumerate(row):
            inc_s[p, c], inc_sign[p, c] = s, sign
    normal, rhs, yy = np.zeros((s_count, s_count)), np.zeros(s_count), 0.0
    for path in files:
        z = np.load(path, allow_pickle=True)
        x = z["positions"].astype(np.float64)
        pinned = z["pinned"]
        if index is not None:
            x = np.einsum("fpkc,pk->fpc", x[:, index], weight)
            pinned = (pinned[index] * weight).sum(axis=1) >= 0.5
        acc = (x[2:] - 2 * x[1:-1] + x[:-2]) / dt**2
        states = x[1:-1]
        acc, states = acc[:: a.every], states[:: a.every]
        y = mass[None, :, None] * (acc - gravity)
        d = states[:, springs[:, 1]] - states[:, springs[:, 0]]
        length = np.linalg.norm(d, axis=2, keepdims=True)
        unit = (length - rest[None, :, None]) * d / length  # force on the first end per unit k
        cols = unit[:, inc_s] * inc_sign[None, :, :, None]  # [F, V, K, 3]
        free = ~pinned
        cols, y, idx = cols[:, free], y[:, free], inc_s[free]
        np.add.at(normal, (idx[:, :, None], idx[:, None, :]), np.einsum("fpic,fpjc->pij", cols, cols))
        np.add.at(rhs, idx, np.einsum("fpic,fpc->pi", cols, y))
        yy += float((y**2).sum())
    ridge = 1e-6 * np.trace(normal) / s_count
    k = np.linalg.solve(normal + ridge * np.eye(s_count), rhs)
    one = np.ones(s_count)
    k_one = (one @ rhs) / (one @ normal @ one)
    explained_one = 1 - (yy - 2 * k_one * (one @ rhs) + k_one**2 * (one @ normal @ one)) / yy
    explained = 1 - (yy - 2 * k @ rhs + k @ normal @ k) / yy
    what = f"a {a.grid} x {a.grid} surrogate grid" if a.grid else "the data mesh's edges"
    print(f"springs on {what}: {s_count}; {len(files)} files, every {a.every}th frame")
    print(f"uniform k = {k_one:.3g} N/m explains {explained_one:.4f} of m(a - g); per-spring k {explained:.4f}")
    print(f"Spearman(fitted k, Young's modulus) = {spearman(k[ranked], truth[ranked]):.3f} "
          f"over {int(ranked.sum())} springs; fitted k 5/50/95 %: {np.percentile(k[ranked], [5, 50, 95]).round(2)}")


if __name__ == "__main__":
    main()
