#!/usr/bin/env python3
"""newton_cloth: cloth rollouts from NVIDIA Newton's VBD cloth solver for springtime to learn from.

A foreign source, not part of springtime: a square sheet built with Newton's
`ModelBuilder.add_cloth_grid` (stable Neo-Hookean membrane triangles plus dihedral bending
edges) and integrated by `newton.solvers.SolverVBD` -- Vertex Block Descent (Chen et al. 2024):
implicit (backward) Euler, each substep solved by Gauss-Seidel sweeps over graph-coloured
vertices, each vertex taking a 3x3 Newton step on its local energy -- on the CPU. That is a
different time integration from warp.sim's explicit semi-implicit Euler (see warp_cloth.py):
no stability limit on the substep, numerical damping from backward Euler and finite
iterations, and a Rayleigh-type damping on the rate of the metric F^T F. After `finalize()`
every triangle gets its own material row (`model.tri_materials`: ke = mu, ka = lambda, kd,
drag, lift), the ke, ka and kd columns scaled by a structured stiffness map: a soft base, two
stiff vertical stripes and a stiff band along the top edge (8x stiffer). SolverVBD reads
`tri_materials[tri_index, 0..2]` per adjacent triangle in its force/Hessian kernel
(newton/_src/solvers/vbd/particle_vbd_kernels.py). Newton is z-up: the sheet starts flat and
at rest in the horizontal x-y plane and falls under gravity [0, 0, -9.81], held by 2-4 kinematic
boundary vertices (mass 0, flag inactive: VBD keeps them where the state says) that follow
smooth random paths for the first half of the take and are then held still; before every
substep their positions are set to the path at the substep's end (the implicit solve is at the
end of the step) and their velocities to its derivative. No ground, no collisions, no self
contact.

Each take is written the way a user would dump it (`np.savez`), in springtime's rollout format:
`positions` [F, N, 3] f32 (frame 0 = start, no velocities), `rest_uv`, `pinned`, `frame_dt`,
`total_mass` (the uniform particle mass times N: the landmarks share it equally, as in the
grid), `width`, `height`, `gravity` ([0, 0, -9.81]), `triangles` and `tri_stiffness` (the
ground-truth per-triangle ke = mu, N/m), plus extra keys springtime ignores (`tri_ka`, `tri_kd`,
`edge_ke`, `pin_indices`). `OUT/source.json` records the simulator, versions, material, every
parameter, the substeps and VBD iterations, the seeds and the wall time.

Install and run (PyPI package `newton`, which pulls in a matching `warp-lang`):

    python3 -m venv /work/venvs/newton
    /work/venvs/newton/bin/pip install newton numpy
    /work/venvs/newton/bin/python benches/foreign/newton_cloth.py OUT --train 16 --test 4 \\
        --seconds 4 --fps 50 --res 25 --size 2.0 --material soft --seed 0
    springtime data check OUT/train

OUT must be empty or new, or hold an earlier output of this script (its source.json), which is
then overwritten.
"""

import argparse
import json
import math
import os
import platform
import shutil
import sys
import time

import numpy as np

GRAVITY = 9.81
DENSITY = 0.3  # kg/m^2
MAP_RATIO = 8.0  # stiff regions / soft base

# Per material: base membrane stiffness ke (N/m: the Lame mu times thickness), area stiffness
# ka = lambda as a multiple of ke, damping kd = beta * ke (the map scales all three), bending
# edge_ke, and the substeps per frame at 50 fps (scaled with 1/fps for other rates) and VBD
# iterations per substep. VBD does not blow up at any substep; the substeps and iterations buy
# convergence instead, and an unconverged solve is softer than tri_ke says (1 s of seed-1 motion:
# soft edge-strain RMS 3.5 % at 5x10, 2.0 % at 10x10, 1.7 % at 20x20 substeps x iterations; stiff
# 0.9 % at 10x10, 0.20 % at 20x20, 0.10 % at 40x40). `tri_stiffness` is the nominal material.
MATERIALS = {
    "soft": dict(tri_ke=120.0, ka_over_ke=1.0, beta=1.0e-3, edge_ke=0.01, edge_kd=0.0, substeps_at_50fps=10, iterations=10),
    "stiff": dict(tri_ke=5000.0, ka_over_ke=1.0, beta=1.0e-3, edge_ke=0.01, edge_kd=0.0, substeps_at_50fps=20, iterations=20),
}


def stiffness_map(u, v, width, height):
    """Map value (1 = soft base, MAP_RATIO = stiff) at rest coordinates (u, v)."""
    stripe = (np.abs(u - 0.3 * width) < 0.08 * width) | (np.abs(u - 0.7 * width) < 0.08 * width)
    band = v > 0.85 * height
    return np.where(stripe | band, MAP_RATIO, 1.0)


def smootherstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def rotation(r):
    """Rotation matrix of rotation vector r (Rodrigues)."""
    th = float(np.linalg.norm(r))
    if th < 1e-12:
        return np.eye(3)
    k = r / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * kx + (1.0 - math.cos(th)) * (kx @ kx)


class PinPath:
    """Smooth random motion of the pinned vertices: a common translation, a rotation about the
    pins' centroid and a contraction towards it (pins never move apart beyond their rest
    distances, so the sheet between them is not torn), each a sum of sinusoids of periods
    0.5-2 s, played through a quintic time warp that starts and stops at rest at t_half; held
    afterwards."""

    def __init__(self, rng, rest, size, t_half):
        self.rest = rest  # [P, 3]
        self.c = rest.mean(axis=0)
        self.t_half = t_half
        k = 3
        self.tp = rng.uniform(0.5, 2.0, size=(k,))
        self.tph = rng.uniform(0, 2 * np.pi, size=(k,))
        # |T| per axis <= 2 * k * 0.05 size = 0.3 size
        self.ta = rng.uniform(-0.05, 0.05, size=(k, 3)) * size
        self.rp = rng.uniform(0.5, 2.0, size=(k,))
        self.rph = rng.uniform(0, 2 * np.pi, size=(k,))
        self.ra = rng.uniform(-0.08, 0.08, size=(k, 3))
        self.sp = rng.uniform(0.5, 2.0)
        self.sa = rng.uniform(0.0, 0.35)

    def _at_tau(self, tau):
        w = 2 * np.pi / self.tp
        tr = ((np.sin(w * tau + self.tph) - np.sin(self.tph))[:, None] * self.ta).sum(axis=0)
        w = 2 * np.pi / self.rp
        rv = ((np.sin(w * tau + self.rph) - np.sin(self.rph))[:, None] * self.ra).sum(axis=0)
        s = 1.0 - self.sa * 0.5 * (1.0 - math.cos(2 * np.pi * tau / self.sp))
        return self.c + tr + (s * (self.rest - self.c)) @ rotation(rv).T

    def position(self, t):
        tau = self.t_half * smootherstep(t / self.t_half) if self.t_half > 0 else 0.0
        return self._at_tau(tau)

    def velocity(self, t, h=1e-5):
        return (self.position(t + h) - self.position(t - h)) / (2 * h)


def boundary_vertices(res):
    return [j * res + i for j in range(res) for i in range(res) if i in (0, res - 1) or j in (0, res - 1)]


def pick_pins(rng, res, size, uv):
    bnd = np.array(boundary_vertices(res))
    count = int(rng.integers(2, 5))
    for _ in range(1000):
        pick = rng.choice(bnd, size=count, replace=False)
        d = np.linalg.norm(uv[pick][:, None] - uv[pick][None], axis=-1)
        if d[np.triu_indices(count, 1)].min() >= 0.25 * size:
            return np.sort(pick)
    return np.sort(pick)


def run_take(wp, newton, args, mat, seed):
    rng = np.random.default_rng(seed)
    res, size = args.res, args.size
    n = res * res
    cell = size / (res - 1)
    particle_mass = DENSITY * size * size / n
    builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=(0.0, 0.0, -GRAVITY))
    ke = mat["tri_ke"]
    # grid (x, y, 0) is already horizontal in z-up; centred on the origin
    builder.add_cloth_grid(
        pos=wp.vec3(-size / 2, -size / 2, 0.0), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
        dim_x=res - 1, dim_y=res - 1, cell_x=cell, cell_y=cell, mass=particle_mass,
        tri_ke=ke, tri_ka=ke * mat["ka_over_ke"], tri_kd=ke * mat["beta"],
        edge_ke=mat["edge_ke"], edge_kd=mat["edge_kd"],
    )
    uv = np.array([[(i % res) * cell, (i // res) * cell] for i in range(n)], dtype=np.float64)
    pins = pick_pins(rng, res, size, uv)
    for i in pins:
        builder.particle_mass[i] = 0.0
        builder.particle_flags[i] = int(builder.particle_flags[i]) & ~int(newton.ParticleFlags.ACTIVE)
    builder.color(include_bending=True)
    model = builder.finalize(device="cpu")
    tris = model.tri_indices.numpy().astype(np.int32)
    cen = uv[tris].mean(axis=1)
    smap = stiffness_map(cen[:, 0], cen[:, 1], size, size)
    mats = model.tri_materials.numpy()
    mats[:, 0] = ke * smap
    mats[:, 1] = ke * mat["ka_over_ke"] * smap
    mats[:, 2] = ke * mat["beta"] * smap
    model.tri_materials.assign(mats)  # in place: the solver reads this array at every step
    assert np.allclose(model.tri_materials.numpy()[:, 0], ke * smap)
    solver = newton.solvers.SolverVBD(model, iterations=mat["iterations"])
    control = model.control()

    q0 = model.particle_q.numpy().astype(np.float64)
    assert np.allclose(q0[:, :2] + size / 2, uv, atol=1e-5) and np.allclose(q0[:, 2], 0.0)
    frames = int(round(args.seconds * args.fps)) + 1
    frame_dt = 1.0 / args.fps
    substeps = max(1, int(math.ceil(mat["substeps_at_50fps"] * 50.0 / args.fps)))
    dt = frame_dt / substeps
    path = PinPath(rng, q0[pins], size, 0.5 * args.seconds)

    s0, s1 = model.state(), model.state()
    out = np.empty((frames, n, 3), dtype=np.float32)
    out[0] = s0.particle_q.numpy()
    for f in range(1, frames):
        for k in range(substeps):
            t1 = (f - 1) * frame_dt + (k + 1) * dt
            q, qd = s0.particle_q.numpy(), s0.particle_qd.numpy()  # CPU arrays: zero-copy views
            q[pins] = path.position(t1)
            qd[pins] = path.velocity(t1)
            s0.clear_forces()
            solver.step(s0, s1, control, None, dt)
            s0, s1 = s1, s0
            q, qd = s0.particle_q.numpy(), s0.particle_qd.numpy()
            q[pins] = path.position(t1)
            qd[pins] = path.velocity(t1)
        out[f] = s0.particle_q.numpy()
    if not np.isfinite(out).all():
        raise RuntimeError(f"take with seed {seed} blew up (non-finite positions)")
    pinned = np.zeros(n, dtype=bool)
    pinned[pins] = True
    take = dict(
        positions=out,
        rest_uv=uv.astype(np.float32),
        pinned=pinned,
        frame_dt=np.float64(frame_dt),
        total_mass=np.float64(particle_mass * n),
        width=np.float64(size),
        height=np.float64(size),
        gravity=np.array([0.0, 0.0, -GRAVITY]),
        triangles=tris,
        tri_stiffness=mats[:, 0].astype(np.float32),
        tri_ka=mats[:, 1].astype(np.float32),
        tri_kd=mats[:, 2].astype(np.float32),
        edge_ke=np.float64(mat["edge_ke"]),
        pin_indices=pins.astype(np.int32),
        seed=np.int64(seed),
    )
    return take, dict(substeps=substeps, dt=dt, particle_mass=particle_mass)


def prepare_out(out):
    if os.path.exists(out):
        if not os.path.isdir(out):
            sys.exit(f"{out} exists and is not a directory")
        entries = os.listdir(out)
        if entries and "source.json" not in entries:
            sys.exit(f"{out} is not empty and holds no source.json of an earlier run; refusing to write there")
        for name in ("train", "test"):
            shutil.rmtree(os.path.join(out, name), ignore_errors=True)
        if "source.json" in entries:
            os.remove(os.path.join(out, "source.json"))
    os.makedirs(os.path.join(out, "train"), exist_ok=True)
    os.makedirs(os.path.join(out, "test"), exist_ok=True)
    # mark the folder as ours at once, so that a rerun after a failure may overwrite it
    with open(os.path.join(out, "source.json"), "w") as fh:
        json.dump(dict(complete=False, script=os.path.basename(__file__)), fh)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out")
    ap.add_argument("--train", type=int, default=16)
    ap.add_argument("--test", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--fps", type=float, default=50.0)
    ap.add_argument("--res", type=int, default=25)
    ap.add_argument("--size", type=float, default=2.0)
    ap.add_argument("--material", choices=sorted(MATERIALS), default="soft")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if not 24 <= args.fps <= 100:
        ap.error("--fps must lie in 24-100")
    if args.res < 3 or args.size <= 0 or args.seconds <= 0:
        ap.error("need --res >= 3, --size > 0, --seconds > 0")
    prepare_out(args.out)

    import warp as wp

    wp.config.log_level = getattr(wp, "LOG_WARNING", 30)  # no per-module compile chatter
    import newton
    import newton.solvers  # noqa: F401

    mat = MATERIALS[args.material]
    start = time.time()
    takes = []
    info = None
    for split, count, tag in (("train", args.train, 0), ("test", args.test, 1)):
        for i in range(count):
            # train and test draw from disjoint seed streams
            seed = int(np.random.SeedSequence([args.seed, tag, i]).generate_state(1)[0])
            t0 = time.time()
            take, info = run_take(wp, newton, args, mat, seed)
            np.savez(os.path.join(args.out, split, f"take_{i:03d}.npz"), **take)
            takes.append(dict(split=split, index=i, seed=seed, pins=take["pin_indices"].tolist(),
                              seconds=round(time.time() - t0, 3)))
            print(f"{split}/take_{i:03d}: {len(take['pin_indices'])} pins, {time.time() - t0:.1f} s", flush=True)
    wall = time.time() - start
    source = dict(
        complete=True,
        simulator="NVIDIA Newton (ModelBuilder.add_cloth_grid + SolverVBD, vertex block descent)",
        package="newton",
        version=newton.__version__,
        warp_lang=wp.__version__,
        numpy=np.__version__,
        python=platform.python_version(),
        device="cpu",
        material=args.material,
        parameters=dict(
            res=args.res, size_m=args.size, density_kg_m2=DENSITY,
            particle_mass_kg=info["particle_mass"] if info else DENSITY * args.size**2 / args.res**2,
            total_mass_kg=DENSITY * args.size**2, gravity_m_s2=[0.0, 0.0, -GRAVITY],
            tri_ke_base_N_m=mat["tri_ke"], tri_ka_base=mat["tri_ke"] * mat["ka_over_ke"],
            tri_kd_base=mat["tri_ke"] * mat["beta"], tri_drag=0.0, tri_lift=0.0,
            edge_ke=mat["edge_ke"], edge_kd=mat["edge_kd"],
            stiffness_map="tri_ke, tri_ka, tri_kd x8 where |u-0.3W|<0.08W or |u-0.7W|<0.08W (stripes) or v>0.85H (top band), at triangle centroids",
            map_ratio=MAP_RATIO,
            pins="2-4 boundary vertices >= 0.25 size apart, mass 0, inactive, set to the path at each substep end; rigid translation (<=0.3 size/axis) + rotation + contraction (<=35%) about their centroid, sums of 3 sinusoids (periods 0.5-2 s) through a quintic time warp over the first half, then held",
            start="flat, at rest, horizontal (x-y plane, z-up), falls under gravity; no ground, no collisions, no self contact",
        ),
        fps=args.fps,
        seconds=args.seconds,
        frames=int(round(args.seconds * args.fps)) + 1,
        substeps_per_frame=info["substeps"] if info else None,
        substep_dt_s=info["dt"] if info else None,
        vbd_iterations=mat["iterations"],
        seed=args.seed,
        seed_rule="take seed = SeedSequence([seed, 0 for train / 1 for test, index]).generate_state(1)[0]",
        takes=takes,
        wall_time_s=round(wall, 3),
    )
    with open(os.path.join(args.out, "source.json"), "w") as fh:
        json.dump(source, fh, indent=2)
    print(f"wrote {len(takes)} takes to {args.out} in {wall:.1f} s")


if __name__ == "__main__":
    main()
