"""How well a bench run's learned stiffness ranks its source's map, on a triangulated quad mesh's
cell sides and cut diagonals apart, beside the strain-compliance map of the training takes.

    python3 benches/foreign/map_ranks.py RUN DATA

RUN is a `springtime train` run directory (its `springs.npz`), DATA the bench set it trained on
(`DATA/train/*.npz` with `triangles` and `tri_stiffness`). A mesh edge that is the longest side of
both its triangles is a quad cell's diagonal (springtime's rule, `cloth.layout = "data"`); the
other edges are the cells' sides. Each spring's true value is that of the source's triangle
holding the spring's midpoint (the first listed, as springtime's `stiffness_map_corr`), and the
compliance map is one over each edge's RMS strain over every training frame. Prints Spearman's
rank correlation of each with the truth, over the sides, the diagonals and all edges. Needs numpy
(any of the bench's environments has it: `~/.cache/springtime-foreign/venv-warp/bin/python`).
"""
import argparse
import glob
from collections import defaultdict
from pathlib import Path

import numpy as np


def ranks(a):
    """Ranks from 0, ties sharing their mean rank."""
    order = np.argsort(a, kind="stable")
    r = np.empty(len(a))
    r[order] = np.arange(len(a))
    _, inverse, counts = np.unique(a, return_inverse=True, return_counts=True)
    sums = np.zeros(len(counts))
    np.add.at(sums, inverse, r)
    return (sums / counts)[inverse]


def spearman(a, b):
    if len(a) < 3:
        return float("nan")
    return float(np.corrcoef(ranks(a), ranks(b))[0, 1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("data", type=Path)
    a = ap.parse_args()
    files = sorted(glob.glob(str(a.data / "train" / "*.npz")))
    if not files:
        raise SystemExit(f"{a.data / 'train'}: no .npz takes")
    first = np.load(files[0])
    for key in ("triangles", "tri_stiffness", "rest_uv"):
        if key not in first:
            raise SystemExit(f"{files[0]}: no key `{key}`")
    tris, truth_per_tri = first["triangles"], first["tri_stiffness"]
    uv = first["rest_uv"].astype(float)

    opposite, triangles_on = defaultdict(list), defaultdict(list)
    for t_index, t in enumerate(tris):
        for i in range(3):
            a_, b_, c_ = t[i], t[(i + 1) % 3], t[(i + 2) % 3]
            edge = (min(a_, b_), max(a_, b_))
            opposite[edge].append(c_)
            triangles_on[edge].append(t_index)
    edges = sorted(opposite)

    def length(p, q):
        return float(np.hypot(*(uv[p] - uv[q])))

    def diagonal(edge):
        far = opposite[edge]
        if len(far) != 2:
            return False
        shared = length(*edge)
        return all(length(v, c) <= shared * (1 + 1e-9) for c in far for v in edge)

    is_diagonal = np.array([diagonal(e) for e in edges])
    # As springtime's `stiffness_map_corr`: the first listed triangle holding the midpoint.
    truth = np.array([truth_per_tri[triangles_on[e][0]] for e in edges])

    springs = np.load(a.run / "springs.npz")
    index = {(min(p, q), max(p, q)): s for s, (p, q) in enumerate(springs["springs"])}
    missing = [e for e in edges if e not in index]
    if missing:
        raise SystemExit(f"{a.run}: {len(missing)} mesh edges have no spring (another mesh?)")
    learned = np.array([springs["k"][index[e]] for e in edges], dtype=float)

    rest = np.array([length(*e) for e in edges])
    e = np.array(edges)
    square_sum, frames = np.zeros(len(edges)), 0
    for f in files:
        x = np.load(f)["positions"].astype(float)
        strain = np.linalg.norm(x[:, e[:, 0]] - x[:, e[:, 1]], axis=2) / rest - 1.0
        square_sum += np.nansum(strain**2, axis=0)
        frames = frames + np.sum(np.isfinite(strain), axis=0)
    rms = np.sqrt(square_sum / np.maximum(frames, 1))
    compliance = 1.0 / np.maximum(rms, 1e-12)

    sides = ~is_diagonal
    print(f"{a.run}: {sides.sum()} sides, {is_diagonal.sum()} diagonals")
    for name, values in (("learned k", learned), ("compliance map", compliance)):
        print(f"  {name:15s} Spearman: sides {spearman(values[sides], truth[sides]):.2f}, "
              f"diagonals {spearman(values[is_diagonal], truth[is_diagonal]):.2f}, "
              f"all edges {spearman(values, truth):.2f}")


if __name__ == "__main__":
    main()
