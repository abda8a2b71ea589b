"""foreign_common: the parts the foreign cloth generators share (numpy only, no simulator).

Imported by blender_cloth.py, warp_cloth.py, newton_cloth.py and mujoco_cloth.py as
`from foreign_common import ...` (Python puts a script's own folder on sys.path): the smooth
random pin path, the pin choice, the stiffness-map layout (two vertical stripes and a top band),
the grid's rest coordinates, the per-take seed streams, the command-line arguments every
generator takes, the output-folder check and the bits of source.json they all write.
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
PERTURB_STREAM = 7  # the SeedSequence key of --perturb's draws (beside the take's seed)

# source.json wording shared by the generators
SEED_RULE = "take seed = SeedSequence([seed, 0 for train / 1 for test, index]).generate_state(1)[0]"
MAP_REGIONS = "|u-0.3W|<0.08W or |u-0.7W|<0.08W (stripes) or v>0.85H (top band), at triangle centroids"
PIN_MOTION = ("rigid translation (<=0.3 size/axis) + rotation + contraction (<=35%) about their centroid, "
              "sums of 3 sinusoids (periods 0.5-2 s) through a quintic time warp over the first half, then held")


# ---------------------------------------------------------------- stiffness map


def stiffness_regions(u, v, width, height):
    """(stripe, band) masks at rest coordinates (u, v): two vertical stripes around 0.3 W and
    0.7 W (half-width 0.08 W) and a band along the top edge (v > 0.85 H)."""
    stripe = (np.abs(u - 0.3 * width) < 0.08 * width) | (np.abs(u - 0.7 * width) < 0.08 * width)
    band = v > 0.85 * height
    return stripe, band


def stiffness_map(u, v, width, height, ratio=MAP_RATIO):
    """Map value (1 = soft base, ratio = stiff) at rest coordinates (u, v)."""
    stripe, band = stiffness_regions(u, v, width, height)
    return np.where(stripe | band, ratio, 1.0)


def perturbed(smap, perturb, seed):
    """The per-triangle map smap times 1 + perturb * N(0, 1) where perturb > 0, drawn from a
    stream of the take's seed of its own (the pins and their paths stay the unperturbed take's):
    the generators' --perturb."""
    if perturb <= 0.0:
        return smap
    noise = np.random.default_rng(np.random.SeedSequence([seed, PERTURB_STREAM])).standard_normal(len(smap))
    out = smap * (1.0 + perturb * noise)
    if (out <= 0.0).any():
        raise ValueError(f"--perturb {perturb}: a triangle's stiffness came out <= 0 (take seed {seed})")
    return out


def map_tri_materials(mats, uv, tris, size, ke, ka_over_ke, beta, perturb=0.0, seed=0):
    """Scale the ke, ka = ke * ka_over_ke and kd = ke * beta columns of Warp-style per-triangle
    material rows mats [M, 5] (in place) by the stiffness map at the triangles' rest centroids
    (uv: rest coordinates of a size x size sheet), each triangle's three by 1 + perturb * N(0, 1)
    where perturb > 0 (drawn from a stream of the take's seed of its own: the pins and their
    paths stay the unperturbed take's). Returns the map (perturbed)."""
    cen = uv[tris].mean(axis=1)
    smap = perturbed(stiffness_map(cen[:, 0], cen[:, 1], size, size), perturb, seed)
    mats[:, 0] = ke * smap
    mats[:, 1] = ke * ka_over_ke * smap
    mats[:, 2] = ke * beta * smap
    return smap


# ---------------------------------------------------------------- pin paths


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


def drive_pins(state, pins, path, t):
    """Set the pinned particles of a Warp/Newton CPU state (its particle_q / particle_qd arrays,
    whose numpy() are zero-copy views) to the path at time t. Returns the positions view."""
    q, qd = state.particle_q.numpy(), state.particle_qd.numpy()
    q[pins] = path.position(t)
    qd[pins] = path.velocity(t)
    return q


# ---------------------------------------------------------------- the grid and its pins


def grid_uv(res, size):
    """Rest coordinates [res * res, 2] (float64) of vertex j * res + i: (i cell, j cell)."""
    cell = size / (res - 1)
    return np.array([[(i % res) * cell, (i // res) * cell] for i in range(res * res)], dtype=np.float64)


def boundary_vertices(res):
    return [j * res + i for j in range(res) for i in range(res) if i in (0, res - 1) or j in (0, res - 1)]


def choose_pins(rng, candidates, uv, size):
    """2-4 distinct vertices out of candidates, at least 0.25 size apart (in uv) where 1000 draws
    find such a set; sorted."""
    count = int(rng.integers(2, 5))
    for _ in range(1000):
        pick = rng.choice(candidates, size=count, replace=False)
        d = np.linalg.norm(uv[pick][:, None] - uv[pick][None], axis=-1)
        if d[np.triu_indices(count, 1)].min() >= 0.25 * size:
            return np.sort(pick)
    return np.sort(pick)


def pin_particles(builder, pins, active_flag):
    """Make the pins kinematic in a Warp/Newton ModelBuilder: mass 0, active_flag cleared."""
    for i in pins:
        builder.particle_mass[i] = 0.0
        builder.particle_flags[i] = int(builder.particle_flags[i]) & ~int(active_flag)


def pick_pins(rng, res, size, uv):
    """2-4 boundary vertices of the res x res grid (vertex j * res + i), >= 0.25 size apart."""
    return choose_pins(rng, np.array(boundary_vertices(res)), uv, size)


# ---------------------------------------------------------------- takes and their seeds


def take_seed(seed, tag, index):
    """The seed of take `index` of a split: train (tag 0) and test (tag 1) draw from disjoint
    seed streams (SEED_RULE)."""
    return int(np.random.SeedSequence([seed, tag, index]).generate_state(1)[0])


def take_plan(args):
    """(split, index, seed) of every take: args.train training takes, then args.test test takes."""
    for split, count, tag in (("train", args.train, 0), ("test", args.test, 1)):
        for i in range(count):
            yield split, i, take_seed(args.seed, tag, i)


def frame_count(args):
    """Frames of a take, frame 0 (the start) included."""
    return int(round(args.seconds * args.fps)) + 1


def rollout(positions, uv, pins, frame_dt, total_mass, size, gravity, triangles, tri_stiffness, **extra):
    """The keys of springtime's rollout format, in the order the generators write them (a
    square sheet: width = height = size), then the generator's extra keys."""
    pinned = np.zeros(len(uv), dtype=bool)
    pinned[pins] = True
    return dict(
        positions=positions,
        rest_uv=uv.astype(np.float32),
        pinned=pinned,
        frame_dt=np.float64(frame_dt),
        total_mass=np.float64(total_mass),
        width=np.float64(size),
        height=np.float64(size),
        gravity=np.array(gravity),
        triangles=triangles,
        tri_stiffness=tri_stiffness,
        **extra,
    )


def tri_material_keys(mats, edge_ke, pins, seed):
    """The extra rollout keys of the Warp-style generators: the other material columns (ka, kd),
    the bending stiffness, the pins and the take's seed."""
    return dict(
        tri_ka=mats[:, 1].astype(np.float32),
        tri_kd=mats[:, 2].astype(np.float32),
        edge_ke=np.float64(edge_ke),
        pin_indices=pins.astype(np.int32),
        seed=np.int64(seed),
    )


def write_takes(args, make_take, digits=1):
    """Simulate and save every take of take_plan(args) as OUT/<split>/take_<i>.npz; make_take(seed)
    returns (take, info). Returns (the takes' records for source.json, the last info)."""
    takes, info = [], None
    for split, i, seed in take_plan(args):
        t0 = time.time()
        take, info = make_take(seed)
        np.savez(os.path.join(args.out, split, f"take_{i:03d}.npz"), **take)
        takes.append(dict(split=split, index=i, seed=seed, pins=take["pin_indices"].tolist(),
                          seconds=round(time.time() - t0, 3)))
        print(f"{split}/take_{i:03d}: {len(take['pin_indices'])} pins, {time.time() - t0:.{digits}f} s", flush=True)
    return takes, info


# ---------------------------------------------------------------- command line and output folder


def add_common_args(ap, materials, fps_type=float, fps_default=50.0, size_default=2.0, helps=None):
    """The arguments every generator takes: out, --train, --test, --seconds, --fps, --res, --size,
    --material, --seed (helps: optional help texts by argument name)."""
    helps = helps or {}
    ap.add_argument("out", help=helps.get("out"))
    ap.add_argument("--train", type=int, default=16, help=helps.get("train"))
    ap.add_argument("--test", type=int, default=4, help=helps.get("test"))
    ap.add_argument("--seconds", type=float, default=4.0, help=helps.get("seconds"))
    ap.add_argument("--fps", type=fps_type, default=fps_default, help=helps.get("fps"))
    ap.add_argument("--res", type=int, default=25, help=helps.get("res"))
    ap.add_argument("--size", type=float, default=size_default, help=helps.get("size"))
    ap.add_argument("--material", choices=sorted(materials), default="soft")
    ap.add_argument("--seed", type=int, default=0)


def check_common_args(ap, args, fps_lo, fps_hi, counts=False):
    """Refuse an fps outside fps_lo-fps_hi, res < 3, size <= 0 or seconds <= 0 (and, with counts,
    negative --train/--test)."""
    if not fps_lo <= args.fps <= fps_hi:
        ap.error(f"--fps must lie in {fps_lo}-{fps_hi}")
    if counts:
        if args.res < 3 or args.size <= 0 or args.seconds <= 0 or args.train < 0 or args.test < 0:
            ap.error("need --res >= 3, --size > 0, --seconds > 0, --train/--test >= 0")
    elif args.res < 3 or args.size <= 0 or args.seconds <= 0:
        ap.error("need --res >= 3, --size > 0, --seconds > 0")


OUT_RULE = ("OUT must be empty or new, or hold an earlier output of this script (its source.json), "
            "which is then overwritten.")


def add_perturb_arg(ap):
    """--perturb EPS of the generators (see perturbed)."""
    ap.add_argument("--perturb", type=float, default=0.0, metavar="EPS",
                    help="multiply each triangle's stiffness and damping by 1 + EPS * N(0, 1), the same takes and pins "
                         "otherwise: the source's own spread, against which a surrogate's error is read "
                         "(benches/foreign/takes_rmse.py)")


def check_perturb_arg(ap, args):
    if not 0.0 <= args.perturb < 0.3:
        ap.error(f"--perturb must lie in [0, 0.3), got {args.perturb}")


def setup(doc, script, materials, fps_lo, fps_hi, counts=False, extra=None, check_extra=None):
    """Parse and check the common arguments (the description: doc's first paragraph), plus the
    generator's own (extra(ap) adds them, check_extra(ap, args) checks them), and prepare the
    output folder for script. Returns the arguments."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0], epilog=OUT_RULE)
    add_common_args(ap, materials)
    if extra:
        extra(ap)
    args = ap.parse_args()
    check_common_args(ap, args, fps_lo, fps_hi, counts=counts)
    if check_extra:
        check_extra(ap, args)
    prepare_out(args.out, script)
    return args


def prepare_out(out, script, subdirs=("train", "test")):
    """Make out ready for a run of script: new, empty, or an earlier output of a generator (its
    source.json), whose subdirs and source.json are removed; then create subdirs and mark the
    folder with an incomplete source.json."""
    if os.path.exists(out):
        if not os.path.isdir(out):
            sys.exit(f"{out} exists and is not a directory")
        entries = os.listdir(out)
        if entries and "source.json" not in entries:
            sys.exit(f"{out} is not empty and holds no source.json of an earlier run; refusing to write there")
        for name in subdirs:
            shutil.rmtree(os.path.join(out, name), ignore_errors=True)
        if "source.json" in entries:
            os.remove(os.path.join(out, "source.json"))
    for name in subdirs:
        os.makedirs(os.path.join(out, name), exist_ok=True)
    # mark the folder as ours at once, so that a rerun after a failure may overwrite it
    with open(os.path.join(out, "source.json"), "w") as fh:
        json.dump(dict(complete=False, script=os.path.basename(script)), fh)


def host_facts(device="cpu"):
    """source.json: the numpy and Python versions (and the device, unless None)."""
    facts = dict(numpy=np.__version__, python=platform.python_version())
    if device is not None:
        facts["device"] = device
    return facts


def add_cloth_grid(wp, builder, args, mat, beta, pos, rot, active_flag, rng):
    """Add the res x res sheet of `mat` through a Warp-style builder's add_cloth_grid (Warp's and
    Newton's take the same arguments) and pin 2-4 of its boundary vertices (drawn from `rng`).
    Returns (uv, pins, particle mass)."""
    res, size = args.res, args.size
    cell = size / (res - 1)
    particle_mass = DENSITY * size * size / (res * res)
    ke = mat["tri_ke"]
    builder.add_cloth_grid(
        pos=pos, rot=rot, vel=wp.vec3(0.0, 0.0, 0.0),
        dim_x=res - 1, dim_y=res - 1, cell_x=cell, cell_y=cell, mass=particle_mass,
        tri_ke=ke, tri_ka=ke * mat["ka_over_ke"], tri_kd=ke * beta,
        edge_ke=mat["edge_ke"], edge_kd=mat["edge_kd"],
    )
    uv = grid_uv(res, size)
    pins = pick_pins(rng, res, size, uv)
    pin_particles(builder, pins, active_flag)
    return uv, pins, particle_mass


def grid_take(positions, uv, pins, args, particle_mass, gravity, tris, mats, mat, seed, hint=""):
    """The rollout of a Warp-style grid's take (`mats`: its tri_materials rows, the map applied);
    refused, naming the seed, where it blew up."""
    if not np.isfinite(positions).all():
        raise RuntimeError(f"take with seed {seed} blew up (non-finite positions){hint}")
    return rollout(positions, uv, pins, 1.0 / args.fps, particle_mass * len(uv), args.size, gravity, tris,
                   mats[:, 0].astype(np.float32), **tri_material_keys(mats, mat["edge_ke"], pins, seed))


def grid_cloth_parameters(args, mat, info, gravity, beta, pins, start):
    """source.json parameters of a Warp-style cloth grid (add_cloth_grid, tri_ke/ka/kd, edges, the
    x8 map on all three) whose takes returned `info` (None: no take ran); `pins` and `start` say
    how the pins are held and how a take starts."""
    particle_mass = info["particle_mass"] if info else DENSITY * args.size**2 / args.res**2
    return dict(
        res=args.res, size_m=args.size, density_kg_m2=DENSITY,
        particle_mass_kg=particle_mass, total_mass_kg=DENSITY * args.size**2, gravity_m_s2=gravity,
        tri_ke_base_N_m=mat["tri_ke"], tri_ka_base=mat["tri_ke"] * mat["ka_over_ke"],
        tri_kd_base=mat["tri_ke"] * beta, tri_drag=0.0, tri_lift=0.0,
        edge_ke=mat["edge_ke"], edge_kd=mat["edge_kd"],
        stiffness_map=f"tri_ke, tri_ka, tri_kd x8 where {MAP_REGIONS}",
        map_ratio=MAP_RATIO,
        pins=f"2-4 boundary vertices >= 0.25 size apart, {pins}; {PIN_MOTION}",
        start=start,
    )


def substep_facts(info):
    """source.json: the substeps per frame and their length, from the takes' `info`."""
    return dict(substeps_per_frame=info["substeps"] if info else None, substep_dt_s=info["dt"] if info else None)


def take_facts(args):
    """source.json: fps, seconds, frames."""
    return dict(fps=args.fps, seconds=args.seconds, frames=frame_count(args))


def write_source(args, takes, wall, simulator, package, version, parameters, device="cpu", **more):
    """Write the finished OUT/source.json (the simulator and its package's version, the host, the
    material, the parameters, more, the base seed and SEED_RULE, then the takes and the wall time)
    and say so."""
    source = dict(complete=True, simulator=simulator, package=package, version=version, **host_facts(device),
                  material=args.material, parameters=parameters, **more, seed=args.seed, seed_rule=SEED_RULE,
                  takes=takes, wall_time_s=round(wall, 3))
    with open(os.path.join(args.out, "source.json"), "w") as fh:
        json.dump(source, fh, indent=2)
    print(f"wrote {len(takes)} takes to {args.out} in {wall:.1f} s")
