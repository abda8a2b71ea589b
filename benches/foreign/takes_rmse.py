#!/usr/bin/env python3
"""How far two folders of the same takes are apart, as `eval` measures a surrogate: the motion
RMSE over every particle (Eq. 14, frame 1 on), the frames' mean up to 0.8 s and over the take,
and over half-second windows, per take and over all.

    python3 benches/foreign/takes_rmse.py A B [--short 0.8] [--json FILE]

A and B hold `.npz` takes of springtime's rollout format with the same file names (the first is
the reference); the takes present in both are compared and must have the same frames, particles
and `frame_dt`. Made to read a source's own spread: the bench's generators re-run their test
takes with the material perturbed (`warp_cloth.py`, `newton_cloth.py`: `--perturb EPS`) or the
solve refined (`newton_cloth.py --refine F`), the same pins and paths otherwise, and this
prints how far those land from the originals: how far the source misses itself, which a
surrogate of that data is not expected to beat at either horizon (the book, Across simulators);
`run.py --spread EPS` adds it to the bench's table. `--json FILE` also writes the means and the
windows there. Needs numpy only (any of the bench's environments:
`~/.cache/springtime-foreign/venv-newton/bin/python`).
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np


def load(path):
    with np.load(path) as z:
        positions = np.asarray(z["positions"], dtype=np.float64)
        dt = float(z["frame_dt"])
    if not np.isfinite(positions).all():
        sys.exit(f"{path}: non-finite positions (hidden markers?); complete takes only")
    return positions, dt


def curve(a, b):
    """Per frame 1.. of two takes [F, N, 3]: the RMS over particles of the distance."""
    return np.sqrt(((a[1:] - b[1:]) ** 2).sum(-1).mean(-1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", type=Path, help="the reference takes")
    ap.add_argument("b", type=Path, help="the same takes, from another run")
    ap.add_argument("--short", type=float, default=0.8, help="the short horizon, s (eval's 0.8)")
    ap.add_argument("--json", type=Path, help="also write the means and the windows to this file")
    args = ap.parse_args()
    for d in (args.a, args.b):
        if not d.is_dir():
            sys.exit(f"{d}: not a directory")
    names = sorted({p.name for p in args.a.glob("*.npz")} & {p.name for p in args.b.glob("*.npz")})
    if not names:
        sys.exit(f"{args.a} and {args.b} share no .npz take by name")
    rows, curves = [], []
    for name in names:
        (xa, dta), (xb, dtb) = load(args.a / name), load(args.b / name)
        if xa.shape != xb.shape or abs(dta - dtb) > 1e-12 * dta:
            sys.exit(f"{name}: {args.a} has {xa.shape} at {dta} s, {args.b} {xb.shape} at {dtb} s: not the same take")
        c = curve(xa, xb)
        t = np.arange(1, len(xa)) * dta
        curves.append((t, c))
        rows.append((name, c[t <= args.short + 1e-9].mean(), c.mean(), c[-1]))
        print(f"{name}: short {rows[-1][1]:.4f} m, whole take {rows[-1][2]:.4f} m, last frame {rows[-1][3]:.4f} m")
    t = curves[0][0]
    half = []
    if any(len(tt) != len(t) for tt, _ in curves):
        print("(the takes differ in length: the windows below are not printed)")
    else:
        mean = np.mean([c for _, c in curves], axis=0)
        half = [float(mean[(t > s + 1e-9) & (t <= s + 0.5 + 1e-9)].mean()) for s in np.arange(0.0, t[-1], 0.5)]
    short, whole = float(np.mean([r[1] for r in rows])), float(np.mean([r[2] for r in rows]))
    windows = ("; half seconds " + " ".join(f"{w:.4f}" for w in half)) if half else ""
    print(f"{len(rows)} takes: short {short:.4f} m, whole take {whole:.4f} m{windows}")
    if args.json:
        args.json.write_text(json.dumps(dict(takes=names, short_s=args.short, short=short, long=whole,
                                             half_seconds=half, per_take=[dict(take=r[0], short=float(r[1]),
                                                                               long=float(r[2])) for r in rows])))


if __name__ == "__main__":
    main()
