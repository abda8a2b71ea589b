#!/usr/bin/env python3
"""fig7_f64_floor: the Fig. 7 motion error of a spring network simulated in float64.

A measurement, not part of springtime. `springtime eval` simulates the surrogate in f32 (Burn's
flex backend); the mass-spring source simulated its rollouts in f64 and stored them in f32. This
script re-simulates each test rollout from its stored first frame with the source's integrator
(semi-implicit Euler, one step per 1 ms frame, Eq. 4 springs, gravity, Rayleigh `-c v`, pinned
particles following the file), in f64, once with the run's `k`, `b` and once with the source's
own, and prints Eq. 14's motion RMSE as `springtime eval` summarises it (the mean and standard
deviation over every rollout's frames from frame 1 up to the horizon).

    python3 benches/fig7_f64_floor.py data/fig7_mass_spring runs/fig7_least_squares [--rollouts N]

Needs NumPy; the run's particles must be the data's landmarks (a grid of the data's size).
"""

import argparse
import glob
import os
import time

import tomllib

import numpy as np


def simulate(z, k, b, rest, springs, mass, rayleigh):
    """Per-frame RMSE against the file's positions of a free rollout from its first frame."""
    x_data, v_data = z["positions"], z["velocities"]
    dt, g = float(z["frame_dt"]), z["gravity"].astype(np.float64)
    pinned = z["pinned"]
    i, j = springs[:, 0], springs[:, 1]
    n = len(pinned)
    x = x_data[0].astype(np.float64)
    v = v_data[0].astype(np.float64)
    errors = []
    for t in range(len(x_data) - 1):
        d = x[j] - x[i]
        length = np.sqrt((d * d).sum(1))
        u = d / length[:, None]
        along = ((v[j] - v[i]) * u).sum(1)
        f = (k * (length - rest) + b * along)[:, None] * u
        force = np.stack(
            [np.bincount(i, f[:, c], n) - np.bincount(j, f[:, c], n) for c in range(3)], 1
        )
        v = v + dt * (force / mass + g - rayleigh / mass * v)
        x = x + dt * v
        x[pinned] = x_data[t + 1][pinned]
        v[pinned] = v_data[t + 1][pinned]
        errors.append(np.sqrt(((x - x_data[t + 1]) ** 2).sum(1).mean()))
    return np.array(errors), dt


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("data", help="the data folder (test_*.npz with the source's springs)")
    ap.add_argument("run", help="a trained run whose springs.npz holds k, b")
    ap.add_argument("--rollouts", type=int, default=16, help="test rollouts simulated")
    a = ap.parse_args()
    files = sorted(glob.glob(os.path.join(a.data, "test_*.npz")))[: a.rollouts]
    if not files:
        raise SystemExit(f"{a.data}: no test_*.npz")
    run = np.load(os.path.join(a.run, "springs.npz"))
    with open(os.path.join(a.run, "config.toml"), "rb") as f:
        rayleigh = float(tomllib.load(f)["sim"]["rayleigh"])
    springs = run["springs"].astype(np.int64)
    rest = run["rest_length"].astype(np.float64)
    mass = float(run["particle_mass"])
    networks = {"run": (run["k"].astype(np.float64), run["b"].astype(np.float64))}
    z0 = np.load(files[0])
    if np.array_equal(z0["springs"], run["springs"]):
        networks["source"] = (z0["spring_k"].astype(np.float64), z0["spring_b"].astype(np.float64))
    start = time.time()
    for name, (k, b) in networks.items():
        curves = []
        for f in files:
            errors, dt = simulate(np.load(f), k, b, rest, springs, mass, rayleigh)
            curves.append(errors)
        times = (np.arange(len(curves[0])) + 1) * dt
        for horizon in (0.8, 8.0):
            e = np.concatenate([c[times <= horizon + 1e-9] for c in curves])
            print(f"{name} network in f64: motion RMSE <= {horizon} s {e.mean():.4e} +- {e.std():.4e} m")
        ends = ", ".join(f"{c[-1]:.2e}" for c in curves)
        print(f"  per rollout at the last frame: {ends}  ({time.time() - start:.0f} s)")


if __name__ == "__main__":
    main()
