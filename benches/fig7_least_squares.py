#!/usr/bin/env python3
"""fig7_least_squares: what training data identifies when the force fit is solved exactly.

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
source's values stored in the files (a mass-spring source), and writes `k`, `b` into the run's
springs.npz, which `springtime eval` then scores. The springs, the particle mass and Rayleigh
damping are the run's; its particles must be the data's landmarks (a grid of the data's size
over a grid source), so that no resampling enters. On other data (an FEM source, 10 ms frames)
the same solve is the best spring network for the frames' mean forces.

    springtime train configs/fig7_mass_spring.toml --out F      # a Fig. 7 run (its data and config)
    cp -r F F_ls
    python3 benches/fig7_least_squares.py data/fig7_mass_spring F_ls --rollouts 32 --every 20
    springtime eval F_ls

Needs NumPy; about 1 GB of memory for the 11,652 x 11,652 normal matrix.
"""

import argparse
import glob
import os
import time

import tomllib

import numpy as np


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="the data folder (train_*.npz with velocities)")
    ap.add_argument("run", help="a copy of a run whose springs.npz gets the fitted k, b")
    ap.add_argument("--rollouts", type=int, default=32, help="training rollouts used")
    ap.add_argument("--every", type=int, default=20, help="use every n-th stored frame")
    ap.add_argument("--k-prior", type=float, default=50.0, help="Tikhonov target of k, N/m")
    ap.add_argument("--b-prior", type=float, default=3.0, help="Tikhonov target of b, N*s/m")
    a = ap.parse_args()
    files = sorted(glob.glob(os.path.join(a.data, "train_*.npz")))[: a.rollouts]
    if not files:
        raise SystemExit(f"{a.data}: no train_*.npz")
    z = np.load(files[0])
    if "velocities" not in z.files:
        raise SystemExit(f"{files[0]}: no `velocities`")
    run_npz = os.path.join(a.run, "springs.npz")
    run = dict(np.load(run_npz))
    with open(os.path.join(a.run, "config.toml"), "rb") as f:
        rayleigh = float(tomllib.load(f)["sim"]["rayleigh"])
    springs = run["springs"].astype(np.int64)
    n_springs = len(springs)
    rest = run["rest_length"].astype(np.float64)
    n_particles = len(run["rest_uv"])
    if len(z["rest_uv"]) != n_particles or np.abs(z["rest_uv"] - run["rest_uv"]).max() > 1e-5:
        raise SystemExit(f"{a.run}: its particles are not the data's landmarks")
    mass = float(run["particle_mass"])
    dt, gravity = float(z["frame_dt"]), z["gravity"]
    truth = "spring_k" in z.files and np.array_equal(z["springs"], run["springs"])
    if truth:
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
    start, rows, truth_residual, force_sq = time.time(), 0, [], 0.0
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
            force_sq += float((force**2).sum())
            if truth and len(truth_residual) < 3:
                true_params = np.concatenate([np.append(k_true, 0)[sp], np.append(b_true, 0)[sp]], axis=1)
                pred = np.einsum("fra,fa->fr", coeff, true_params)
                truth_residual.append(np.sqrt(((pred - force) ** 2).mean() / (force**2).mean()))
            rows += 3 * len(free)
    print(f"{len(files)} rollouts, {rows} force rows in {time.time() - start:.0f} s")
    if truth:
        print(f"the source's own k, b leave a relative residual of {max(truth_residual):.1e}")
    a_mat, b_vec = normal[:n, :n], rhs[:n]
    diag = np.diag(a_mat)
    lam = 1e-9 * diag.mean()
    prior = np.concatenate([np.full(n_springs, a.k_prior), np.full(n_springs, a.b_prior)])
    sol = np.linalg.solve(a_mat + lam * np.eye(n), b_vec + lam * prior)
    k, b = sol[:n_springs], sol[n_springs:]
    residual = np.sqrt(max(sol @ (a_mat @ sol) - 2 * sol @ b_vec + force_sq, 0.0) / force_sq)
    print(
        f"relative force residual {residual:.3g}; {int((diag == 0).sum())} parameters no frame "
        f"constrains; k 5/50/95 % {np.percentile(k, [5, 50, 95]).round(2)}, "
        f"b {np.percentile(b, [5, 50, 95]).round(3)}; {time.time() - start:.0f} s"
    )
    if truth:
        rmse = lambda e: float(np.sqrt((e**2).mean()))
        print(f"rmse_k {rmse(k - k_true):.4g} N/m, rmse_b {rmse(b - b_true):.4g} N*s/m")
    run["k"], run["b"] = k.astype(np.float32), b.astype(np.float32)
    tmp = run_npz + ".tmp.npz"
    np.savez(tmp, **run)
    os.replace(tmp, run_npz)
    print(f"wrote k, b into {run_npz}")


if __name__ == "__main__":
    main()
