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
"""

import math
import time

import numpy as np

from foreign_common import (GRAVITY, PinPath, add_cloth_grid, add_perturb_arg, check_perturb_arg, drive_pins, frame_count,
                            grid_cloth_parameters, grid_take, map_tri_materials, setup, substep_facts, take_facts,
                            write_source, write_takes)

# Per material: base membrane stiffness ke (N/m: the Lame mu times thickness), area stiffness
# ka = lambda as a multiple of ke, damping kd = beta * ke (the map scales all three), bending
# edge_ke, and the substeps per frame at 50 fps (scaled with 1/fps for other rates) and VBD
# iterations per substep. VBD does not blow up at any substep; the substeps and iterations buy
# convergence instead, and an unconverged solve is softer than tri_ke says (1 s of seed-1 motion:
# soft edge-strain RMS 3.5 % at 5x10, 2.0 % at 10x10, 1.7 % at 20x20 substeps x iterations; stiff
# 0.9 % at 10x10, 0.20 % at 20x20, 0.10 % at 40x40). `tri_stiffness` is the nominal material.
# The motion is not converged either: `--refine 2` (40x40) moves the stiff set's first two 3-s
# test takes 0.097 m at 0.8 s and 0.317 m over the take from the 20x20 ones, the soft set at
# 30 fps 0.035 m and 0.085 m (four takes; the book, Across simulators, "How far the sources miss
# their own takes").
MATERIALS = {
    "soft": dict(tri_ke=120.0, ka_over_ke=1.0, beta=1.0e-3, edge_ke=0.01, edge_kd=0.0, substeps_at_50fps=10, iterations=10),
    "stiff": dict(tri_ke=5000.0, ka_over_ke=1.0, beta=1.0e-3, edge_ke=0.01, edge_kd=0.0, substeps_at_50fps=20, iterations=20),
}


def run_take(wp, newton, args, mat, seed):
    rng = np.random.default_rng(seed)
    res, size = args.res, args.size
    n = res * res
    builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=(0.0, 0.0, -GRAVITY))
    ke = mat["tri_ke"]
    # grid (x, y, 0) is already horizontal in z-up; centred on the origin
    uv, pins, particle_mass = add_cloth_grid(wp, builder, args, mat, mat["beta"], wp.vec3(-size / 2, -size / 2, 0.0),
                                             wp.quat_identity(), newton.ParticleFlags.ACTIVE, rng)
    builder.color(include_bending=True)
    model = builder.finalize(device="cpu")
    tris = model.tri_indices.numpy().astype(np.int32)
    mats = model.tri_materials.numpy()
    smap = map_tri_materials(mats, uv, tris, size, ke, mat["ka_over_ke"], mat["beta"], args.perturb, seed)
    model.tri_materials.assign(mats)  # in place: the solver reads this array at every step
    assert np.allclose(model.tri_materials.numpy()[:, 0], ke * smap)
    solver = newton.solvers.SolverVBD(model, iterations=mat["iterations"] * args.refine)
    control = model.control()

    q0 = model.particle_q.numpy().astype(np.float64)
    assert np.allclose(q0[:, :2] + size / 2, uv, atol=1e-5) and np.allclose(q0[:, 2], 0.0)
    frames = frame_count(args)
    frame_dt = 1.0 / args.fps
    substeps = max(1, int(math.ceil(mat["substeps_at_50fps"] * 50.0 / args.fps))) * args.refine
    dt = frame_dt / substeps
    path = PinPath(rng, q0[pins], size, 0.5 * args.seconds)

    s0, s1 = model.state(), model.state()
    out = np.empty((frames, n, 3), dtype=np.float32)
    out[0] = s0.particle_q.numpy()
    for f in range(1, frames):
        for k in range(substeps):
            t1 = (f - 1) * frame_dt + (k + 1) * dt
            drive_pins(s0, pins, path, t1)  # CPU arrays: zero-copy views
            s0.clear_forces()
            solver.step(s0, s1, control, None, dt)
            s0, s1 = s1, s0
            drive_pins(s0, pins, path, t1)
        out[f] = s0.particle_q.numpy()
    take = grid_take(out, uv, pins, args, particle_mass, [0.0, 0.0, -GRAVITY], tris, mats, mat, seed)
    return take, dict(substeps=substeps, dt=dt, particle_mass=particle_mass)


def extra_args(ap):
    add_perturb_arg(ap)
    ap.add_argument("--refine", type=int, default=1, metavar="F",
                    help="F times the material's substeps and VBD iterations: how far the takes are from a "
                         "converged solve (the same takes and pins otherwise)")


def check_extra_args(ap, args):
    check_perturb_arg(ap, args)
    if args.refine < 1:
        ap.error(f"--refine must be 1 or more, got {args.refine}")


def main():
    args = setup(__doc__, __file__, MATERIALS, 24, 100, extra=extra_args, check_extra=check_extra_args)

    import warp as wp

    wp.config.log_level = getattr(wp, "LOG_WARNING", 30)  # no per-module compile chatter
    import newton
    import newton.solvers  # noqa: F401

    mat = MATERIALS[args.material]
    start = time.time()
    takes, info = write_takes(args, lambda seed: run_take(wp, newton, args, mat, seed))
    wall = time.time() - start
    write_source(
        args, takes, wall,
        simulator="NVIDIA Newton (ModelBuilder.add_cloth_grid + SolverVBD, vertex block descent)",
        package="newton",
        version=newton.__version__,
        parameters=grid_cloth_parameters(
            args, mat, info, [0.0, 0.0, -GRAVITY], mat["beta"],
            pins="mass 0, inactive, set to the path at each substep end",
            start="flat, at rest, horizontal (x-y plane, z-up), falls under gravity; no ground, no collisions, "
                  "no self contact"),
        warp_lang=wp.__version__,
        **take_facts(args),
        **substep_facts(info),
        vbd_iterations=mat["iterations"] * args.refine,
        perturb=args.perturb,
        refine=args.refine,
    )


if __name__ == "__main__":
    main()
