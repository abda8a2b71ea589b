#!/usr/bin/env python3
"""Capture-grade copies of a bench set: position noise and missing markers, as motion capture
delivers a cloth's tracks.

    python capture.py SRC DST --noise 0.002 --missing 0.1 --seed 0

Every take under SRC/train and SRC/test is written to the same place under DST with

- Gaussian noise of `--noise` m (standard deviation per axis, independent per frame) on the free
  markers' positions; pinned markers are the rig's known path and stay exact;
- `--missing` of the free markers' samples hidden: half as independent dropouts, half as
  occlusion bursts (a disc over a fifth of the sheet's width, in the rest rectangle, that hides
  every marker under it for 0.1-0.4 s at a time and moves between bursts);
- hidden positions written as NaN and a `visible` [F, N] bool mask (springtime's rollout format);
- the noise's standard deviation as `position_noise` (m per axis: the marker accuracy a capture
  states, which springtime's least-squares fit takes out);
- stored velocities dropped (a capture has none).

Other keys (`triangles`, `tri_stiffness`, ...) are kept, so the Spearman against the source's map
still works; `index.json` is copied and `source.json` gains a `capture` record. Needs numpy.
"""

import argparse
import json
import shutil
from pathlib import Path

import numpy as np


def corrupt(take: dict, noise: float, missing: float, rng: np.random.Generator) -> dict:
    x = np.asarray(take["positions"], dtype=np.float64)
    frames, n, _ = x.shape
    pinned = np.asarray(take["pinned"]).astype(bool)
    free = ~pinned
    uv = np.asarray(take["rest_uv"], dtype=np.float64)
    dt = float(take["frame_dt"])
    size = float(max(take["width"], take["height"]))
    seen = np.ones((frames, n), dtype=bool)
    # Half of the missing share as independent dropouts.
    seen &= ~((rng.random((frames, n)) < missing / 2) & free)
    # The other half as occlusion bursts: a disc hiding every free marker under it.
    radius = 0.2 * size / 2
    under = lambda c: (np.linalg.norm(uv - c, axis=1) < radius) & free
    target = missing * frames * free.sum()
    hidden = lambda: (~seen[:, free]).sum()
    for _ in range(10_000):
        if hidden() >= target:
            break
        length = max(1, int(round(rng.uniform(0.1, 0.4) / dt)))
        start = int(rng.integers(0, max(1, frames - length)))
        centre = uv.min(axis=0) + rng.random(2) * (uv.max(axis=0) - uv.min(axis=0))
        seen[start:start + length, under(centre)] = False
    # Every marker seen at least once (a track that never appears is no track).
    for i in np.where(~seen.any(axis=0))[0]:
        seen[int(rng.integers(0, frames)), i] = True
    noisy = x + rng.normal(0.0, noise, x.shape) * free[None, :, None]
    noisy[~seen] = np.nan
    out = {k: v for k, v in take.items() if k not in ("positions", "velocities", "visible")}
    out["positions"] = noisy.astype(np.float32)
    out["visible"] = seen
    # The marker accuracy, as a capture states it: springtime's least-squares fit takes it out.
    out["position_noise"] = np.float64(noise)
    return out


def load_take(f, dropped):
    """A take's arrays; a foreign key stored as a pickled object array (tpcloth's `material`) is
    left out and named in `dropped`, since unpickling a file runs code from it."""
    take = {}
    with np.load(f, allow_pickle=False) as d:
        for k in d.files:
            try:
                take[k] = d[k]
            except ValueError as e:
                if "allow_pickle" not in str(e):  # a damaged array, not a pickled one
                    raise SystemExit(f"{f}: key `{k}`: {e}")
                dropped.add(k)
    return take


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--noise", type=float, default=0.002, help="m, standard deviation per axis")
    ap.add_argument("--missing", type=float, default=0.1, help="share of free markers' samples hidden")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    if a.dst.exists():
        shutil.rmtree(a.dst)
    rng = np.random.default_rng(a.seed)
    stats, dropped = [], set()
    for split in ("train", "test"):
        src = a.src / split
        if not src.is_dir():
            continue
        (a.dst / split).mkdir(parents=True)
        for f in sorted(src.iterdir()):
            if f.suffix == ".npz":
                take = load_take(f, dropped)
                out = corrupt(take, a.noise, a.missing, rng)
                free = ~np.asarray(take["pinned"]).astype(bool)
                stats.append(float((~out["visible"][:, free]).mean()))
                np.savez_compressed(a.dst / split / f.name, **out)
            else:
                shutil.copy(f, a.dst / split / f.name)
    if dropped:
        print(f"not copied: {', '.join(sorted(dropped))} (pickled object arrays, read only with "
              "allow_pickle; springtime ignores foreign keys)")
    source = a.src / "source.json"
    record = json.loads(source.read_text()) if source.exists() else {}
    record["capture"] = {"noise_m": a.noise, "missing": a.missing, "seed": a.seed,
                         "hidden_share_measured": float(np.mean(stats)) if stats else None,
                         "from": str(a.src)}
    (a.dst / "source.json").write_text(json.dumps(record, indent=1))
    print(f"{a.dst}: {len(stats)} takes, {100 * np.mean(stats):.1f} % of free markers' samples hidden, "
          f"noise {1000 * a.noise:g} mm")


if __name__ == "__main__":
    main()
