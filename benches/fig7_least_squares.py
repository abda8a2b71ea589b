#!/usr/bin/env python3
"""fig7_least_squares: what the Fig. 7 training data identifies when the force fit is solved exactly.

A measurement, not part of springtime. With the data's stored velocities and the source's own
integrator (semi-implicit Euler, one step per 1 ms frame), every free particle's force at a
stored frame is known exactly, `m (v[t+1] - v[t]) / dt`, and it is linear in the springs' `k`
and `b` (Eq. 4):

    m (v[t+1] - v[t]) / dt - m g + c v  =  sum_s  k_s (l_s - L_s) u_s  +  b_s ((v_j - v_i) . u_s) u_s

So the teacher-forced force loss (`train.force_on = "target"`) is a linear least-squares
problem. This script builds its normal equations over every `--every`-th frame of the first
`--rollouts` training rollouts (frames at a stored segment's end are left out: the next one is
not stored), solves them (a 1e-9 relative Tikhonov term towards the config's initial 50 N/m and
3 N*s/m keeps a spring no frame stretches at its guess), prints the recovery against the
source's values stored in the files, and with `--springs` writes `k`, `b` into a copy of a
run's springs.npz, which `springtime eval` then scores.

    springtime train configs/fig7_mass_spring.toml --out F      # a Fig. 7 run (its data and config)
    cp -r F F_ls
    python3 benches/fig7_least_squares.py data/fig7_mass_spring --rollouts 32 --every 20 \\
        --springs F_ls/springs.npz
    springtime eval F_ls

Needs NumPy; about 1 GB of memory for the 11,652 x 11,652 normal matrix.
"""

import argparse
import glob
import os
import time

import numpy as np


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="the Fig. 7 data folder (train_*.npz with velocities)")
    ap.add_argument("--rollouts", type=int, default=32, help="training rollouts used")
    ap.add_argument("--every", type=int, default=20, help="use every n-th stored frame")
    ap.add_argument("--k-prior", type=float, default=50.0, help="Tikhonov target of k, N/m")
    ap.add_argument("--b-prior", type=float, default=3.0, help="Tikhonov target of b, N*s/m")
    ap.add_argument("--springs", help="a run's springs.npz to overwrite with the fitted k, b")
    a = ap.parse_args()
    files = sorted(glob.glob(os.path.join(a.data, "train_*.npz")))[: a.rollouts]
    if not files:
        raise SystemExit(f"{a.data}: no train_*.npz")
    z = np.load(files[0])
    for key in ("velocities", "spring_k", "spring_b"):
        if key not in z.files:
            raise SystemExit(f"{files[0]}: no `{key}` (a mass-spring source's training file)")
    springs = z["springs"].astype(np.int64)
    n_springs = len(springs)
    uv = z["rest_uv"].astype(np.float64)
    rest = np.linalg.norm(uv[springs[:, 1]] - uv[springs[:, 0]], axis=1)
    n_particles = len(uv)
    mass = float(z["total_mass"]) / n_particles
    dt, gravity, rayleigh = float(z["frame_dt"]), z["gravity"], float(z["rayleigh"])
    k_true, b_true = z["spring_k"].astype(np.float64), z["spring_b"].astype(np.float64)

    # Each particle's springs (padded with a dummy spring n_springs) and the sign of their pull.
    incident = [[] for _ in range(n_particles)]
    for s, (i, j) in enumerate(springs):
        incident[i].append((s, 1.0))
        incident[j].append((s, -1.0))
    degree = max(len(x) for x in incident)
    spring_of = np.full((n_particles, degree), n_springs, np.int64)
    sign = np.zeros((n_particles, degree))
    for i, x in enumerate(incident):
        for d, (s, sg) in enumerate(x):
            spring_of[i, d], sign[i, d] = s, sg

    n = 2 * n_springs  # k then b; column n collects the padding
    normal = np.zeros((n + 1, n + 1))
    rhs = np.zeros(n + 1)
    start, rows, truth_residual = time.time(), 0, []
    for f in files:
        z = np.load(f)
        x_all = z["positions"].astype(np.float64)
        v_all = z["velocities"].astype(np.float64)
        free = np.where(~z["pinned"])[0]
        # Stored windows `[start, length]` (`source.storage = "clips"`), else the whole rollout.
        segments = z["segments"] if "segments" in z.files else [(0, len(x_all))]
        frames, offset = [], 0
        for _, length in segments:
            frames.extend(range(offset, offset + length - 1, a.every))
            offset += length
        sp = spring_of[free]
        cols = np.concatenate([sp, np.where(sp < n_springs, sp + n_springs, n)], axis=1)
        cols = np.where(cols == n_springs, n, cols)
        for t in frames:
            x, v = x_all[t], v_all[t]
            d = x[springs[:, 1]] - x[springs[:, 0]]
            length = np.linalg.norm(d, axis=1)
            u = d / length[:, None]
            dv = v[springs[:, 1]] - v[springs[:, 0]]
            per_k = np.vstack([(length - rest)[:, None] * u, np.zeros(3)])
            per_b = np.vstack([(dv * u).sum(1)[:, None] * u, np.zeros(3)])
            coeff = np.concatenate(
                [per_k[sp] * sign[free][:, :, None], per_b[sp] * sign[free][:, :, None]], axis=1
            ).transpose(0, 2, 1)  # particles x 3 x 2 degree
            force = (mass * (v_all[t + 1] - v) / dt - mass * gravity + rayleigh * v)[free]
            np.add.at(normal, (cols[:, :, None], cols[:, None, :]), np.einsum("fra,frb->fab", coeff, coeff))
            np.add.at(rhs, cols, np.einsum("fra,fr->fa", coeff, force))
            if len(truth_residual) < 3:
                truth = np.concatenate([np.append(k_true, 0)[sp], np.append(b_true, 0)[sp]], axis=1)
                pred = np.einsum("fra,fa->fr", coeff, truth)
                truth_residual.append(np.sqrt(((pred - force) ** 2).mean() / (force**2).mean()))
            rows += 3 * len(free)
    print(
        f"{len(files)} rollouts, {rows} force rows in {time.time() - start:.0f} s; "
        f"the source's own k, b leave a relative residual of {max(truth_residual):.1e}"
    )
    a_mat, b_vec = normal[:n, :n], rhs[:n]
    diag = np.diag(a_mat)
    lam = 1e-9 * diag.mean()
    prior = np.concatenate([np.full(n_springs, a.k_prior), np.full(n_springs, a.b_prior)])
    sol = np.linalg.solve(a_mat + lam * np.eye(n), b_vec + lam * prior)
    k, b = sol[:n_springs], sol[n_springs:]
    rmse = lambda e: float(np.sqrt((e**2).mean()))
    print(
        f"rmse_k {rmse(k - k_true):.4g} N/m, rmse_b {rmse(b - b_true):.4g} N*s/m "
        f"({int((diag == 0).sum())} parameters no frame constrains; {time.time() - start:.0f} s)"
    )
    if a.springs:
        run = dict(np.load(a.springs))
        if not np.array_equal(run["springs"], springs):
            raise SystemExit(f"{a.springs}: another spring list than the data's")
        run["k"], run["b"] = k.astype(np.float32), b.astype(np.float32)
        tmp = a.springs + ".tmp.npz"
        np.savez(tmp, **run)
        os.replace(tmp, a.springs)
        print(f"wrote k, b into {a.springs}")


if __name__ == "__main__":
    main()
