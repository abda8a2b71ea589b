#!/usr/bin/env python3
"""warp_cloth: cloth rollouts from NVIDIA Warp's `warp.sim` for springtime to learn from.

A foreign source, not part of springtime: a square sheet built with
`warp.sim.ModelBuilder.add_cloth_grid` (FEM triangles with Warp's stable Neo-Hookean membrane
plus dihedral bending edges), integrated by `warp.sim.SemiImplicitIntegrator` (symplectic
Euler, explicit forces) on the CPU. After `finalize()` every triangle gets its own material row
(`model.tri_materials`: ke, ka, kd, drag, lift), all three elastic/damping columns scaled by a
structured stiffness map: a soft base, two stiff vertical stripes and a stiff band along the top
edge (8x stiffer). The sheet starts flat and at rest in the horizontal x-z plane (Warp is y-up)
and falls under gravity, held by 2-4 kinematic boundary vertices (mass 0, flag inactive) that
follow smooth random paths for the first half of the take and are then held still; their
positions and velocities are written into the state before every substep. No ground, no
collisions.

Each take is written the way a Warp user would dump it (`np.savez`), in springtime's rollout
format: `positions` [F, N, 3] f32 (frame 0 = start, no velocities), `rest_uv`, `pinned`,
`frame_dt`, `total_mass` (the uniform particle mass times N: the landmarks share it equally, as
in Warp's grid), `width`, `height`, `gravity` ([0, -9.81, 0]), `triangles` and
`tri_stiffness` (the ground-truth per-triangle ke, N/m), plus extra keys springtime ignores
(`tri_ka`, `tri_kd`, `edge_ke`, `pin_indices`). `OUT/source.json` records the simulator,
versions, material, every parameter, the substeps per frame, the seeds and the wall time.

Install and run (pin warp-lang 1.7.x: warp.sim was deprecated after it in favour of Newton and
is gone from later releases; run here with 1.7.2 on the CPU):

    python3 -m venv /work/venvs/warp
    /work/venvs/warp/bin/pip install warp-lang==1.7.2 numpy
    /work/venvs/warp/bin/python benches/foreign/warp_cloth.py OUT --train 16 --test 4 \\
        --seconds 4 --fps 50 --res 25 --size 2.0 --material soft --seed 0
    springtime data check OUT/train
"""

import math
import time

import numpy as np

from foreign_common import (GRAVITY, PinPath, add_cloth_grid, add_perturb_arg, check_perturb_arg, drive_pins, frame_count,
                            grid_cloth_parameters, grid_take, map_tri_materials, setup, substep_facts, take_facts,
                            write_source, write_takes)

# Per material: base membrane stiffness ke (N/m, Warp's tri_ke = Lame mu times thickness),
# area stiffness ka as a multiple of ke, stiffness-proportional damping kd = beta * ke (beta in s),
# bending edge_ke, and the substeps per frame at 50 fps for the default 25 x 25 grid of 2 m (scaled
# with 1/fps, and with (res - 1) / size for finer grids, whose beta shrinks by the same factor).
# Explicit integration: the substep must resolve the stiffest (8x) triangles, and the damping must
# stay below ~0.1 substep (beta / dt). Measured: soft (ke 80-150) blows up at 20 substeps and runs
# at 40, stiff at 120 and runs at 200; beta 3e-4 (soft, 40 substeps) or 3e-5 (stiff, 200) went
# unstable too (strains of 100+ % or non-finite).
MATERIALS = {
    "soft": dict(tri_ke=120.0, ka_over_ke=1.0, beta=4.0e-5, edge_ke=0.01, edge_kd=0.0, substeps_at_50fps=50),
    "stiff": dict(tri_ke=5000.0, ka_over_ke=1.0, beta=1.0e-5, edge_ke=0.01, edge_kd=0.0, substeps_at_50fps=250),
}


def run_take(wp, sim, args, mat, seed):
    rng = np.random.default_rng(seed)
    res, size = args.res, args.size
    n = res * res
    builder = sim.ModelBuilder(up_vector=(0.0, 1.0, 0.0), gravity=-GRAVITY)
    # grid (x, y, 0) -> world (x, 0, y): rotate +90 degrees about x; centred on the origin
    rot = wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), math.pi / 2)
    ke = mat["tri_ke"]
    # finer or smaller sheets carry lighter particles: the stiffest mode's frequency grows as
    # (res - 1) / size, so the substeps grow with it and the damping's beta shrinks with it
    refine = max(1.0, (res - 1) / 24.0 * 2.0 / size)
    beta = mat["beta"] / refine
    uv, pins, particle_mass = add_cloth_grid(wp, builder, args, mat, beta, wp.vec3(-size / 2, 0.0, -size / 2), rot,
                                             sim.model.PARTICLE_FLAG_ACTIVE, rng)
    model = builder.finalize(device="cpu")
    model.ground = False
    model.particle_max_radius = 0.0  # no particle-particle contact
    tris = model.tri_indices.numpy().astype(np.int32)
    mats = model.tri_materials.numpy()
    map_tri_materials(mats, uv, tris, size, ke, mat["ka_over_ke"], beta, args.perturb, seed)
    model.tri_materials = wp.array(mats, dtype=float, device="cpu")

    q0 = model.particle_q.numpy().astype(np.float64)
    assert np.allclose(q0[:, 0] + size / 2, uv[:, 0], atol=1e-5) and np.allclose(q0[:, 2] + size / 2, uv[:, 1], atol=1e-5)
    frames = frame_count(args)
    frame_dt = 1.0 / args.fps
    substeps = max(1, int(math.ceil(mat["substeps_at_50fps"] * 50.0 / args.fps * refine)))
    dt = frame_dt / substeps
    path = PinPath(rng, q0[pins], size, 0.5 * args.seconds)

    integ = sim.SemiImplicitIntegrator()
    s0, s1 = model.state(), model.state()
    out = np.empty((frames, n, 3), dtype=np.float32)
    out[0] = s0.particle_q.numpy()
    for f in range(1, frames):
        for k in range(substeps):
            t = (f - 1) * frame_dt + k * dt
            drive_pins(s0, pins, path, t)
            s0.clear_forces()
            integ.simulate(model, s0, s1, dt)
            s0, s1 = s1, s0
        out[f] = drive_pins(s0, pins, path, f * frame_dt)
    take = grid_take(out, uv, pins, args, particle_mass, [0.0, -GRAVITY, 0.0], tris, mats, mat, seed,
                     hint="; raise the substeps")
    return take, dict(substeps=substeps, dt=dt, particle_mass=particle_mass, beta=beta)


def main():
    args = setup(__doc__, __file__, MATERIALS, 24, 100, extra=add_perturb_arg, check_extra=check_perturb_arg)

    import warp as wp

    wp.config.quiet = True
    wp.init()
    import warp.sim as sim

    mat = MATERIALS[args.material]
    start = time.time()
    takes, info = write_takes(args, lambda seed: run_take(wp, sim, args, mat, seed))
    wall = time.time() - start
    write_source(
        args, takes, wall,
        simulator="NVIDIA Warp warp.sim (ModelBuilder.add_cloth_grid + SemiImplicitIntegrator)",
        package="warp-lang",
        version=wp.__version__,
        parameters=grid_cloth_parameters(
            args, mat, info, [0.0, -GRAVITY, 0.0], info["beta"] if info else mat["beta"],
            pins="mass 0, inactive",
            start="flat, at rest, horizontal (x-z plane), falls under gravity; no ground, no collisions"),
        **take_facts(args),
        **substep_facts(info),
        perturb=args.perturb,
    )


if __name__ == "__main__":
    main()
