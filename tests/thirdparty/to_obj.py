#!/usr/bin/env python3
"""to_obj: a rollout .npz as a folder of OBJ frames, written the way a DCC tool exports them.

Stands in for "an OBJ sequence exported from another program": y-up axes (Blender's and
Maya's OBJ default: (x, y, z) -> (x, z, -y)), texture coordinates normalised to the unit
square, `f v/vt` corners, six decimals, one file per frame named `<name>_<frame>.obj` with
unpadded frame numbers. Prints the `springtime import obj` flags that recover the data
(`--frame-dt`, `--mass`, `--pinned`, `--gravity`).

    python3 to_obj.py data/tp/train/rollout_000.npz /tmp/objs/rollout_000
"""

import argparse
import os

import numpy as np


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("rollout")
    ap.add_argument("out")
    a = ap.parse_args()
    d = np.load(a.rollout, allow_pickle=True)
    pos = np.asarray(d["positions"], dtype=np.float64)
    uv = np.asarray(d["rest_uv"], dtype=np.float64)
    tris = np.asarray(d["triangles"])
    uv = (uv - uv.min(axis=0)) / (uv.max(axis=0) - uv.min(axis=0))
    os.makedirs(a.out, exist_ok=True)
    name = os.path.basename(os.path.normpath(a.out))
    for f in range(pos.shape[0]):
        y_up = np.stack([pos[f, :, 0], pos[f, :, 2], -pos[f, :, 1]], axis=1)
        lines = ["# exported by to_obj.py (y up)", f"o {name}"]
        lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in y_up]
        lines += [f"vt {u:.6f} {v:.6f}" for u, v in uv]
        lines += [f"f {i + 1}/{i + 1} {j + 1}/{j + 1} {k + 1}/{k + 1}" for i, j, k in tris]
        with open(os.path.join(a.out, f"{name}_{f}.obj"), "w") as fh:
            fh.write("\n".join(lines) + "\n")
    g = np.asarray(d["gravity"], dtype=np.float64) if "gravity" in d.files else np.array([0, 0, -9.81])
    g_up = [g[0], g[2], -g[1]]
    pinned = ",".join(str(i) for i in np.flatnonzero(d["pinned"]))
    print(
        f"--frame-dt {float(d['frame_dt'])!r} --mass {float(d['total_mass'])!r} "
        f"--pinned {pinned} --gravity={g_up[0]:g},{g_up[1]:g},{g_up[2]:g}"
    )


if __name__ == "__main__":
    main()
