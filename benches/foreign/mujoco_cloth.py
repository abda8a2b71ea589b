#!/usr/bin/env python3
"""mujoco_cloth: cloth rollouts from MuJoCo's flex cloth (`flexcomp`) for springtime to learn from.

A foreign source, not part of springtime: a square sheet built as a MuJoCo `<flexcomp
type="grid" dim="2" dof="full">` -- every vertex a body with three slide joints, the
triangles carrying MuJoCo's built-in 2-D flex elasticity (`<elasticity young poisson thickness
damping elastic2d="both">`: the geometrically nonlinear membrane on the squared edge
elongations, plus MuJoCo's thin-plate bending on the flap stencils) -- integrated by
`mj_step` with MuJoCo's semi-implicit `Euler` integrator on the CPU (explicit in the flex
forces on every version, so the timestep resolves the stiffest triangles; MuJoCo 4 refuses
`implicit`/`implicitfast` for an elastic flex). MuJoCo's elasticity parameters
are per flex, but the compiler turns them into a per-element stiffness matrix: for a 2-D
element the 3x3 edge metric (21 slots per element, upper triangle, in `model.flex_stiffness`,
from `flex_stiffnessadr` where the version has it) that `mj_passive` multiplies by the squared
edge elongations every step (MuJoCo 4's `discrete` integrator reads it for its stiffness
derivative too). The force, and MuJoCo's Rayleigh damping, which is folded into the
same elongations, are linear in that metric, so after compiling every element's 21 slots are
scaled by a structured stiffness map: a soft base, two stiff vertical stripes and a stiff band
along the top edge (8x stiffer). The bending stencils stay uniform (the map is the membrane's).
Checked by hanging the sheet from its top corners: mid-height vertical edges strain ~6-24x less
in the stripes than in the soft base with the map, ~1.5x without it.

MuJoCo is z-up: the sheet starts flat and at rest in the horizontal x-y plane and falls under
gravity [0, 0, -9.81], held by 2-4 boundary vertices that follow smooth random paths for the
first half of the take and are then held still. They stay ordinary flex vertices (MuJoCo 4
refuses mocap bodies in an elastic flex, and `<pin>` fixes a vertex to its parent body); their
slide-joint positions and velocities are overwritten with the path before every `mj_step`, so
every force MuJoCo computes sees them on the path (for the take they also get 1e6x their mass
and gravity compensation, so that a step moves them by no more than the path does). No ground, contacts disabled (`<flag
contact="disable"/>`, flex contype/conaffinity 0, no self collision).

Each take is written the way a MuJoCo user would dump it (`np.savez`), in springtime's rollout
format: `positions` [F, N, 3] f32 (`data.flexvert_xpos`, in MuJoCo's flex vertex order; frame
0 = start, no velocities), `rest_uv` (the vertices' rest positions `flex_vert0`-style from the
compiled model, shifted to a (0, 0) min corner), `pinned`, `frame_dt`, `total_mass` (the
flexcomp's `mass`, shared equally by the vertices), `width`, `height`, `gravity` ([0, 0,
-9.81]), `triangles` (`model.flex_elem`) and `tri_stiffness` (the ground-truth membrane
stiffness per triangle, young x thickness x map, N/m), plus extra keys springtime ignores
(`tri_map`, `pin_indices`, `seed`, `pin_step_drift`: how far one step moved a pin off its path). `OUT/source.json` records the simulator, versions,
material, every parameter, the timestep and steps per frame, the seeds and the wall time.

Install and run (developed on mujoco 4.0.0; also runs on 3.3.7, whose membrane comes out ~1.6-2x
softer for the same young: the nominal `tri_stiffness` is the same, the motion is not):

    python3 -m venv /work/venvs/mujoco
    /work/venvs/mujoco/bin/pip install mujoco numpy
    /work/venvs/mujoco/bin/python benches/foreign/mujoco_cloth.py OUT --train 16 --test 4 \\
        --seconds 4 --fps 50 --res 25 --size 2.0 --material soft --seed 0
    springtime data check OUT/train
"""

import math
import time

import numpy as np

from foreign_common import (DENSITY, GRAVITY, MAP_RATIO, MAP_REGIONS, PIN_MOTION, PinPath, add_perturb_arg,
                            check_perturb_arg, choose_pins, frame_count, perturbed, rollout, setup, stiffness_map,
                            take_facts, write_source, write_takes)

PIN_MASS_FACTOR = 1.0e6  # driven vertices: inert inside MuJoCo's implicit step
THICKNESS = 1.0e-3  # m; membrane stiffness = young * thickness, bending ~ young * thickness^3

# Per material: Young's modulus (Pa; times THICKNESS the base membrane stiffness in N/m),
# Poisson ratio, MuJoCo's elasticity damping (s: Rayleigh, stiffness-proportional, on the rate
# of the squared elongations) and the timestep for the default 25 x 25 sheet of 2 m (scaled
# with the edge length for finer grids: the stiffest mode's frequency grows as (res-1)/size).
# Semi-implicit Euler is explicit in the flex forces: the timestep must resolve the 8x regions
# and keep the damping below ~h*beta*omega_max^2 < 1. Measured on the 25 x 25 sheet hanging
# from two corners (with the map): stiff (young 6e6, beta 2e-5) runs at 1e-4 s, blows up at
# 1.25e-4 s, and at 1e-4 s with beta 5e-5 rings; young 1.3e7 blew up even at 5e-5 s with beta
# 2e-4. Soft (young 3e5) runs at 5e-4 s with beta 5e-5 and 4e-4 s with beta 1e-4; the
# timesteps below keep a margin of ~1.25-2x.
MATERIALS = {
    "soft": dict(young=3.0e5, poisson=0.3, damping=1.0e-4, timestep=2.5e-4),
    "stiff": dict(young=6.0e6, poisson=0.3, damping=2.0e-5, timestep=8.0e-5),
}


def pick_pins(rng, uv, size):
    """2-4 distinct boundary vertices at least 0.25 size apart."""
    eps = 1e-6 * size
    bnd = np.flatnonzero((uv[:, 0] < eps) | (uv[:, 1] < eps) | (uv[:, 0] > size - eps) | (uv[:, 1] > size - eps))
    return choose_pins(rng, bnd, uv, size)


def integrator_name(mujoco):
    """MuJoCo's semi-implicit Euler: every version integrates flex elasticity explicitly
    under it (MuJoCo 4 only treats it implicitly under its new 'discrete' integrator and
    refuses 'implicit'/'implicitfast' for an elastic flex; 3.x's 'implicitfast' is explicit in
    the flex too), so one integrator runs on 3.x and 4.x (their membranes still differ)."""
    return "Euler"


def model_xml(args, mat, timestep, integrator):
    res, size = args.res, args.size
    cell = size / (res - 1)
    mass = DENSITY * size * size
    return f"""
<mujoco model="springtime_cloth">
  <option timestep="{timestep!r}" integrator="{integrator}" gravity="0 0 {-GRAVITY!r}">
    <flag contact="disable"/>
  </option>
  <worldbody>
    <flexcomp name="cloth" type="grid" count="{res} {res} 1" spacing="{cell!r} {cell!r} {cell!r}"
              dim="2" dof="full" mass="{mass!r}" radius="{0.1 * cell!r}">
      <elasticity young="{mat['young']!r}" poisson="{mat['poisson']!r}" thickness="{THICKNESS!r}"
                  damping="{mat['damping']!r}" elastic2d="both"/>
      <edge equality="false" stiffness="0" damping="0"/>
      <contact contype="0" conaffinity="0" selfcollide="none"/>
    </flexcomp>
  </worldbody>
</mujoco>
"""


def element_stiffness(model):
    """The compiled per-element 2-D stiffness metrics as a writable [nelem, 21] view."""
    ne = int(model.flex_elemnum[0])
    flat = model.flex_stiffness.reshape(-1)  # 3.x: [nflexelem, 21]; 4.x: [nflexstiffness]
    if hasattr(model, "flex_stiffnessadr"):
        adr = int(model.flex_stiffnessadr[0])
    else:
        adr = 21 * int(model.flex_elemadr[0])
    if adr < 0 or adr + 21 * ne > flat.size:
        raise RuntimeError(f"unexpected flex_stiffness layout: {flat.size} values, adr {adr}, {ne} elements")
    view = flat[adr:adr + 21 * ne].reshape(ne, 21)
    assert np.shares_memory(view, model.flex_stiffness), "flex_stiffness view is a copy"
    return view


def build(mujoco, args, mat):
    """Compile the sheet and apply the stiffness map. Returns (model, facts)."""
    # the stiffest mode's frequency grows as 1/edge (vertex mass ~ edge^2, membrane spring
    # constant ~ young * thickness whatever the edge): the timestep scales with the edge length,
    # up to 3x the 25 x 25 one on coarser sheets (a 9 x 9 CI take)
    refine = max(1.0 / 3.0, (args.res - 1) / 24.0 * 2.0 / args.size)
    timestep = mat["timestep"] / refine
    frame_dt = 1.0 / args.fps
    steps = max(1, int(math.ceil(frame_dt / timestep - 1e-9)))
    timestep = frame_dt / steps
    model = mujoco.MjModel.from_xml_string(model_xml(args, mat, timestep, integrator_name(mujoco)))
    assert model.nflex == 1 and model.flex_dim[0] == 2
    n = int(model.flex_vertnum[0])
    assert n == args.res * args.res
    vb = model.flex_vertbodyid[model.flex_vertadr[0]:model.flex_vertadr[0] + n].copy()
    # every vertex its own body with three slide joints (x, y, z), child of the world
    assert (model.body_jntnum[vb] == 3).all() and (model.body_parentid[vb] == 0).all()
    rest = model.body_pos[vb].copy()  # parent = world: rest positions in world
    assert np.abs(rest[:, 2]).max() < 1e-9
    uv = rest[:, :2] - rest[:, :2].min(axis=0)
    tris = model.flex_elem[model.flex_elemdataadr[0]:model.flex_elemdataadr[0] + 3 * model.flex_elemnum[0]]
    tris = tris.reshape(-1, 3).astype(np.int32)
    cen = uv[tris].mean(axis=1)
    smap = stiffness_map(cen[:, 0], cen[:, 1], args.size, args.size)
    k = element_stiffness(model)
    if not (np.abs(k).max(axis=1) > 0).all():
        raise RuntimeError("some elements have no stiffness metric (elasticity not compiled?)")
    k *= smap[:, None]
    jnt = model.body_jntadr[vb]
    qadr = model.jnt_qposadr[jnt]
    dadr = model.jnt_dofadr[jnt]
    for a in range(3):  # the three slide joints of each vertex body are x, y, z in order
        assert np.allclose(model.jnt_axis[jnt + a], np.eye(3)[a])
        assert (model.jnt_qposadr[jnt + a] == qadr + a).all() and (model.jnt_dofadr[jnt + a] == dadr + a).all()
    total_mass = DENSITY * args.size * args.size  # the flexcomp's mass, shared by the vertices
    assert abs(float(model.body_mass[vb].sum()) - total_mass) < 1e-9 * total_mass
    return model, dict(n=n, vertbody=vb, rest=rest, uv=uv, tris=tris, smap=smap, qadr=qadr, dadr=dadr,
                       timestep=timestep, steps=steps, total_mass=total_mass)


def run_take(mujoco, model, facts, args, seed):
    rng = np.random.default_rng(seed)
    size = args.size
    rest, uv = facts["rest"], facts["uv"]
    pins = pick_pins(rng, uv, size)
    path = PinPath(rng, rest[pins], size, 0.5 * args.seconds)
    pq = (facts["qadr"][pins][:, None] + np.arange(3)).reshape(-1)
    pd = (facts["dadr"][pins][:, None] + np.arange(3)).reshape(-1)
    rest_p = rest[pins].reshape(-1)

    # the pinned vertices are driven, not simulated: within a step MuJoCo's implicit solve must
    # not move them, so they get PIN_MASS_FACTOR x their mass and gravity compensation for the
    # take (both read from the model at run time); with --perturb every element's metric (its
    # stiffness and the damping folded into it) gets the take's own factor; restored afterwards
    vb = facts["vertbody"][pins]
    mass0, grav0 = model.body_mass[vb].copy(), model.body_gravcomp[vb].copy()
    metric = element_stiffness(model)
    metric0 = metric.copy()
    factor = perturbed(np.ones(len(metric)), args.perturb, seed)
    model.body_mass[vb] = mass0 * PIN_MASS_FACTOR
    model.body_gravcomp[vb] = 1.0
    metric *= factor[:, None]
    try:
        return _simulate(mujoco, model, facts, args, seed, pins, path, pq, pd, rest_p, facts["smap"] * factor)
    finally:
        model.body_mass[vb] = mass0
        model.body_gravcomp[vb] = grav0
        metric[...] = metric0


def _simulate(mujoco, model, facts, args, seed, pins, path, pq, pd, rest_p, smap):
    size, n, uv = args.size, facts["n"], facts["uv"]
    data = mujoco.MjData(model)
    k_before = model.flex_stiffness.copy()
    mujoco.mj_setConst(model, data)  # constants that depend on the masses
    assert np.array_equal(model.flex_stiffness, k_before), "mj_setConst rewrote flex_stiffness"
    frames = frame_count(args)
    frame_dt = 1.0 / args.fps
    steps, dt = facts["steps"], facts["timestep"]
    out = np.empty((frames, n, 3), dtype=np.float32)

    def set_pins(t):
        data.qpos[pq] = path.position(t).reshape(-1) - rest_p
        data.qvel[pd] = path.velocity(t).reshape(-1)

    vadr = int(model.flex_vertadr[0])
    drift = 0.0  # how far MuJoCo's step moved a pin off its path (before the next override)
    set_pins(0.0)
    mujoco.mj_fwdPosition(model, data)
    out[0] = data.flexvert_xpos[vadr:vadr + n]
    for f in range(1, frames):
        for s in range(steps):
            t = (f - 1) * frame_dt + s * dt
            set_pins(t)
            mujoco.mj_step(model, data)
            if data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number:
                # MuJoCo resets the state after a blow-up: the positions alone would not show it
                raise RuntimeError(f"take with seed {seed} went unstable at t = {t:.4f} s (MuJoCo reset the state); lower the timestep")
            drift = max(drift, float(np.abs(data.qpos[pq] + rest_p - path.position(t + dt).reshape(-1)).max()))
        set_pins(f * frame_dt)
        mujoco.mj_fwdPosition(model, data)  # flexvert_xpos of the state after the last step
        out[f] = data.flexvert_xpos[vadr:vadr + n]
        if not np.isfinite(out[f]).all():
            raise RuntimeError(f"take with seed {seed} blew up at frame {f} (non-finite positions); lower the timestep")
    ke = mat_ke(args) * smap
    take = rollout(out, uv, pins, frame_dt, facts["total_mass"], size, [0.0, 0.0, -GRAVITY], facts["tris"],
                   ke.astype(np.float32))
    take.update(
        tri_map=smap.astype(np.float32),
        pin_indices=pins.astype(np.int32),
        seed=np.int64(seed),
        pin_step_drift=np.float64(drift),
    )
    return take


def mat_ke(args):
    return MATERIALS[args.material]["young"] * THICKNESS


def main():
    args = setup(__doc__, __file__, MATERIALS, 10, 1000, counts=True, extra=add_perturb_arg,
                 check_extra=check_perturb_arg)

    import mujoco

    mat = MATERIALS[args.material]
    start = time.time()
    model, facts = build(mujoco, args, mat)
    takes, _ = write_takes(args, lambda seed: (run_take(mujoco, model, facts, args, seed), None), digits=2)
    wall = time.time() - start
    ke = mat_ke(args)
    write_source(
        args, takes, wall,
        simulator="MuJoCo flexcomp grid (dim 2, dof full), built-in 2-D flex elasticity, mj_step",
        package="mujoco",
        version=mujoco.__version__,
        parameters=dict(
            res=args.res, size_m=args.size, density_kg_m2=DENSITY,
            vertex_mass_kg=facts["total_mass"] / facts["n"], total_mass_kg=facts["total_mass"],
            gravity_m_s2=[0.0, 0.0, -GRAVITY],
            young_base_Pa=mat["young"], poisson=mat["poisson"], thickness_m=THICKNESS,
            membrane_stiffness_base_N_m=ke, elasticity_damping_s=mat["damping"], elastic2d="both",
            edge_stiffness=0.0, edge_damping=0.0, edge_equality=False,
            stiffness_map="the 21 flex_stiffness slots of every element (stretch metric; the damping is folded into it) "
                          f"x8 where {MAP_REGIONS}; bending uniform",
            map_ratio=MAP_RATIO,
            tri_stiffness="young * thickness * map, N/m",
            pins="2-4 boundary vertices >= 0.25 size apart (ordinary flex vertices: slide-joint qpos and qvel "
                 f"overwritten with the path before every mj_step); {PIN_MOTION}",
            start="flat, at rest, horizontal (x-y plane, z up), falls under gravity; no ground, contacts disabled",
        ),
        integrator=integrator_name(mujoco),
        perturb=args.perturb,
        timestep_s=facts["timestep"],
        steps_per_frame=facts["steps"],
        **take_facts(args),
    )


if __name__ == "__main__":
    main()
