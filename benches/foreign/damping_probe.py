"""What a bench run's surrogate does under other damping models: a NumPy copy of springtime's
step (semi-implicit Euler, Eq. 5, with the run's substeps, masses and pins) that replays a run's
learned springs on a bench set's takes with the drag changed and an isotropic viscosity on the
mesh's edges added, and prints the motion RMSE as `eval` measures it (Eq. 14, every particle,
the frames' mean up to 0.8 s and over the take) and over half-second windows.

    python3 benches/foreign/damping_probe.py RUN DATA [--takes N] [--drag C]
        [--viscosity NU | --viscosity-per-k BETA | --viscosity-source SCALE] [--project]
        [--uniform K,B] [--damping-per-k BETA] [--k-scale F] [--shear-scale S[,S...]]
        [--substeps N] [--implicit-damping SWEEPS]
        [--bending KB[,KB...]] [--area KA[,KA...]] [--compression C[,C...]
        [--compression-on edges|diagonals|all]] [--hinge-compression C[,C...]] [--map source|FILE [--map-share S[,S...]]
        [--map-on sides|all]] [--diagonals-from-sides] [--pins linear|cubic]

RUN is a `springtime train` run directory (`springs.npz`, `config.toml`), DATA a directory of the
bench's takes (`DATA/*.npz`). The surrogate's damping is each spring's `b` along the spring, the
drag `-c v` (`sim.rayleigh`, the run's by default) and, without a viscosity option, the run's own
isotropic viscosity `sim.viscosity` (`beta k_s (v_b - v_a)` on every spring). The viscosity is a damper
`nu (v_j - v_i)` on every edge of the data's triangles: the whole relative velocity, rotations
and out-of-plane motion included, as Warp's FEM triangles damp (`k_damp * dF/dt`, rest area
weighted). `--viscosity NU` puts the same `nu` on every edge, `--viscosity-per-k BETA` BETA times
the `k` of the spring along it; `--viscosity-source SCALE` reads
the source's own damping off the takes (`tri_kd`, written by `warp_cloth.py`) and splits each
triangle's `kd * area * |dF/dt|^2` into its edges with the cotangent weights
(`nu_e = SCALE * sum kd cot(theta) / 2` over the edge's triangles, theta the opposite angle).
`--project` applies the viscosity along the springs instead (added to the matching springs' `b`),
`--uniform K,B` replays one `k` and `b` on every spring instead of the run's, and
`--damping-per-k BETA` sets each spring's `b` to `BETA * k` (stiffness-proportional damping, as
MuJoCo's elasticity damping), `--k-scale F` multiplies every spring's `k`, `--shear-scale S`
the shear springs' (a cell's diagonals, `springs.npz` family 1; a row, one rollout per value).
`--implicit-damping SWEEPS` integrates the springs' `b` by backward Euler instead (each substep
solves `(M + h C) v = M v*`, `C` the dampers along the springs' current directions, by SWEEPS
damped Jacobi sweeps), so a `b` far past what the explicit step's substeps allow stays stable.
`--pins cubic` moves the pinned particles between two frames along the Catmull-Rom spline
through the frames (continuous velocity, exact for constant acceleration) instead of
springtime's straight line at constant velocity, whose velocity jumps at every frame.

Two terms the surrogate does not have, to measure what they would be worth before building them:
`--bending KB` adds a quadratic bending energy on every interior edge of the data's triangles
(Bergou et al. 2006, discrete-shell weights: `1/2 KB 3|e|^2 / (A1 + A2) theta^2`, the hinge's
angle `theta` linearised about the flat rest sheet, so the forces are linear in the positions and
vanish under rigid motions), and `--area KA` an area term `1/2 KA (A - A0)^2 / A0` on every
triangle (a membrane's resistance to changing its area, which springs carry only through their
lengths). `--compression C` makes springs push back with `C k` when shorter than at rest (0:
they pull only; `--compression-on` picks which: the data's mesh edges, the cells' diagonals (the
run's shear springs, `springs.npz` family 1), or every spring; the surrogate has it since as
`sim.shear_compression` on its shear springs).
Without either option the rollouts replay the run's own `sim.shear_compression` on its shear
springs, as the run steps; `--compression` replaces it (a row's `1`: every spring as in tension).
`--hinge-compression C` splits that softening between a cell's two diagonals: the one that is no
edge of the data's triangles (the hinge spring across the cell's triangulated diagonal) pushes
back with `C k`, the other with the run's own `sim.shear_compression`. A triangle mesh folds
freely along its triangles' diagonal, which shortens the cell's other diagonal, and not along
the other, which would shorten an edge; springs on both diagonals that resist compression alike
resist both folds alike.
Each takes a comma-separated row and runs one rollout per value (per pair).

What a stiffness map is worth to the motion: `--map source` blends the takes' own map
(`tri_stiffness`, each vertex the mean of its triangles', each spring the mean of its ends') into
the run's `k` by each share of `--map-share` (each family, the cells' sides and their diagonals,
keeps its mean `k`: `k (1 - S + S m / mean m)`), `--map FILE` a springs `.npz`'s `k` instead (the
run's `springs.learned.npz`, the map a run set aside), `--map-on sides` on the sides alone; and
`--diagonals-from-sides` shapes each shear spring (a cell's diagonal) by its cell's sides, the
diagonals' mean kept (the run's `k`, or with `--map` the map's): one map for the cell, where a
source's diagonals are read worse than its sides. A scratch
tool for the book's damping measurements (Results, Other simulators): it does not replace `eval`, which it matches to a few per cent (f64 here, f32
there). Needs numpy (any of the bench's environments:
`~/.cache/springtime-foreign/venv-warp/bin/python`); about 3 minutes for twelve 3 s takes at 189
substeps on one core.
"""
import argparse
import itertools
import re
import time
from pathlib import Path

import numpy as np

SHORT = 0.8  # s, eval's short horizon


def load_takes(data, count):
    files = sorted(Path(data).glob("*.npz"))[:count]
    if not files:
        raise SystemExit(f"{data}: no .npz takes")
    takes = [np.load(f) for f in files]
    positions = np.stack([t["positions"] for t in takes]).astype(np.float64)  # B F N 3
    if not np.isfinite(positions).all():
        raise SystemExit(f"{data}: hidden markers (NaN positions); the probe takes complete takes only")
    if "velocities" in takes[0].files:
        raise SystemExit(f"{data}: stored velocities; the probe starts as eval does without them only")
    pinned = np.stack([t["pinned"] for t in takes])
    return takes[0], positions, pinned, float(takes[0]["frame_dt"])


def mesh_edges(triangles, rest_uv, kd=None):
    """Each edge of the triangles once, and its cotangent share of the triangles' `kd`."""
    weight = {}
    for t, tri in enumerate(triangles):
        for a, b, o in ((tri[0], tri[1], tri[2]), (tri[1], tri[2], tri[0]), (tri[2], tri[0], tri[1])):
            e1, e2 = rest_uv[a] - rest_uv[o], rest_uv[b] - rest_uv[o]
            cot = (e1 @ e2) / abs(e1[0] * e2[1] - e1[1] * e2[0])
            key = (min(a, b), max(a, b))
            weight[key] = weight.get(key, 0.0) + (0.0 if kd is None else 0.5 * kd[t] * cot)
    return np.array(list(weight.keys()), dtype=int), np.array(list(weight.values()))


def triangle_areas(triangles, rest_uv):
    """Each triangle's rest area."""
    e1 = rest_uv[triangles[:, 1]] - rest_uv[triangles[:, 0]]
    e2 = rest_uv[triangles[:, 2]] - rest_uv[triangles[:, 0]]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def hinge_stencils(triangles, rest_uv):
    """Each interior edge's linearised dihedral angle on the flat rest sheet: the four vertices
    (the edge's ends, then its two opposite vertices) and weights K with K . h the hinge's angle
    for heights h off the sheet (K annihilates affine maps), and the discrete-shell weight
    3 |e|^2 / (A1 + A2); the quadratic bending energy is 1/2 kb w |K . x|^2 (Bergou et al. 2006)."""
    opposite, area = {}, {}
    for tri, a in zip(triangles, triangle_areas(triangles, rest_uv)):
        for i, j, o in ((tri[0], tri[1], tri[2]), (tri[1], tri[2], tri[0]), (tri[2], tri[0], tri[1])):
            key = (min(i, j), max(i, j))
            opposite.setdefault(key, []).append(o)
            area[key] = area.get(key, 0.0) + a
    quads, weights, scale = [], [], []
    for (i, j), ops in opposite.items():
        if len(ops) != 2:
            continue
        e = rest_uv[j] - rest_uv[i]
        el2 = e @ e
        ks = []
        for o in ops:
            r = rest_uv[o] - rest_uv[i]
            d = abs(e[0] * r[1] - e[1] * r[0]) / np.sqrt(el2)
            t = (r @ e) / el2
            ks.append((1.0 / d, t))
        (kc, tc), (kd, td) = ks
        quads.append((i, j, ops[0], ops[1]))
        weights.append((-(1 - tc) * kc - (1 - td) * kd, -tc * kc - td * kd, kc, kd))
        scale.append(3.0 * el2 / area[(i, j)])
    return np.array(quads, dtype=int), np.array(weights), np.array(scale)


def particle_weights(config, first, n):
    """Each particle's mass over the mean (springtime's `cloth.masses`): lumped rest areas or 1."""
    if re.search(r'masses\s*=\s*"equal"', config):
        return np.ones(n)
    tri = first["triangles"].astype(int)
    area = triangle_areas(tri, first["rest_uv"].astype(np.float64))
    w = np.zeros(n)
    for c in range(3):
        w += np.bincount(tri[:, c], area / 3.0, n)
    return w / w.mean()


def batch_rows(index, batch, n):
    """The rows of the flattened [B * N] particles that `index` [M] names in every clip, [B * M]."""
    return ((np.arange(batch) * n)[:, None] + index).ravel()


def add_at(out, rows, force):
    """Adds `force` [B, M, 3] onto the rows `rows` [B * M] of `out` [B * N, 3]."""
    flat = force.reshape(-1, 3)
    for c in range(3):
        out[:, c] += np.bincount(rows, flat[:, c], len(out))


def scatter(pair_force, ia, ib, size):
    """Sums `pair_force` [B, E, 3] (the force on each pair's first end) onto both ends."""
    out = np.zeros((size, 3))
    add_at(out, ia, pair_force)
    add_at(out, ib, -pair_force)
    return out


def area_forces(pos, tri, corners, area0, ka, out):
    """Adds the forces of an area term on every triangle, `1/2 ka (A - A0)^2 / A0`, at `pos`
    [B, N, 3] to `out` [B * N, 3] (`corners`: each corner's rows, `batch_rows`)."""
    a, b, c = pos[:, tri[:, 0]], pos[:, tri[:, 1]], pos[:, tri[:, 2]]
    cross = np.cross(b - a, c - a)
    twice = np.linalg.norm(cross, axis=-1, keepdims=True)
    normal = cross / twice
    coef = -ka * (0.5 * twice - area0[None, :, None]) / area0[None, :, None]
    # dA/dx_i = 1/2 n x (x_k - x_j) for the triangle (i, j, k) counter-clockwise about n
    for rows, pj, pl in ((corners[0], b, c), (corners[1], c, a), (corners[2], a, b)):
        add_at(out, rows, 0.5 * np.cross(normal, pl - pj) * coef)


def damping_solve(vstar, pos, springs, b, sa, sb, mass_i, h, iterations, free):
    """The springs' damping by backward Euler: `(M + h C) v = M v*`, `C` the springs' dampers
    `b d d^T` along their current directions, by `iterations` damped Jacobi sweeps (weight 2/3,
    each particle's diagonal `m + h sum b` over its springs; the pinned particles keep `v*`)."""
    batch, n, _ = vstar.shape
    d = pos[:, springs[:, 1]] - pos[:, springs[:, 0]]
    dhat = d / np.linalg.norm(d, axis=-1, keepdims=True)
    bsum = np.bincount(springs[:, 0], b, n) + np.bincount(springs[:, 1], b, n)
    diag = (mass_i + h * bsum)[None, :, None]
    m = mass_i[None, :, None]
    v = vstar.copy()
    for _ in range(iterations):
        w = v[:, springs[:, 1]] - v[:, springs[:, 0]]
        fd = dhat * (b[None, :, None] * (w * dhat).sum(-1, keepdims=True))
        f = scatter(fd, sa, sb, batch * n).reshape(batch, n, 3)
        v = v + (2.0 / 3.0) * (m * (vstar - v) + h * f) / diag * free
    return v


def pin_path(x, j, dt, pins="linear"):
    """The path the frames `x` [B, F, N, 3] give a particle through frame `j` (1 <= j < F - 1):
    a function of `t` (0-1 of the way through the frame) returning the position and velocity
    there. `linear`: the straight line from frame j to j + 1 at constant velocity, as
    springtime's step; `cubic`: the Catmull-Rom spline through frames j - 1 to j + 2 (frame j + 2
    extrapolated past the last), exact for a path of constant acceleration."""
    here, nxt = x[:, j], x[:, j + 1]
    if pins == "linear":
        velocity = (nxt - here) / dt
        return lambda t: (here * (1.0 - t) + nxt * t, velocity)
    after = x[:, j + 2] if j + 2 < x.shape[1] else 2.0 * nxt - here
    m0, m1 = 0.5 * (nxt - x[:, j - 1]), 0.5 * (after - here)

    def at(t):
        position = ((2 * t**3 - 3 * t**2 + 1) * here + (t**3 - 2 * t**2 + t) * m0
                    + (3 * t**2 - 2 * t**3) * nxt + (t**3 - t**2) * m1)
        velocity = ((6 * t**2 - 6 * t) * here + (3 * t**2 - 4 * t + 1) * m0
                    + (6 * t - 6 * t**2) * nxt + (3 * t**2 - 2 * t) * m1) / dt
        return position, velocity
    return at


def rollout(x, pinned, dt, substeps, springs, k, b, rest, mass, weight, gravity, drag, edges, nu,
            hinge=None, kb=0.0, area=None, ka=0.0, kc=None, implicit=0, pins="linear"):
    """Free rollouts from frame 0 of `x` [B, F, N, 3] (velocities by central differences), the
    pinned particles on the data's path; returns the positions [B, F - 1, N, 3] from frame 1.
    With `implicit` sweeps the springs' `b` is integrated by backward Euler (`damping_solve`).
    `pins`: the pinned particles between two frames on a straight line at constant velocity
    (`linear`, as springtime's step) or on the Catmull-Rom spline through the frames (`cubic`)."""
    batch, frames, n, _ = x.shape
    size = batch * n
    sa, sb = batch_rows(springs[:, 0], batch, n), batch_rows(springs[:, 1], batch, n)
    ea, eb = batch_rows(edges[:, 0], batch, n), batch_rows(edges[:, 1], batch, n)
    if kb:
        quads, kw, scale = hinge
        hq = [batch_rows(quads[:, c], batch, n) for c in range(4)]
    if ka:
        tri, area0 = area
        corners = [batch_rows(tri[:, c], batch, n) for c in range(3)]
    h = dt / substeps
    free = (~pinned)[..., None].astype(np.float64)
    pin = 1.0 - free
    inv_w = (1.0 / weight)[None, :, None]
    pos = x[:, 1].copy()
    vel = (x[:, 2] - x[:, 0]) / (2.0 * dt)
    out = [pos.copy()]
    for j in range(1, frames - 1):
        path = pin_path(x, j, dt, pins)
        for s in range(substeps):
            t = (s + 1) / substeps
            target, pin_v = path(t)
            pin_v = pin_v * pin
            d = pos[:, springs[:, 1]] - pos[:, springs[:, 0]]
            w = vel[:, springs[:, 1]] - vel[:, springs[:, 0]]
            length = np.linalg.norm(d, axis=-1, keepdims=True)
            stiff = k[None, :, None] if kc is None else np.where(length < rest[None, :, None], kc[None, :, None], k[None, :, None])
            coef = stiff * (1.0 - rest[None, :, None] / length)
            if not implicit:
                coef = coef + b[None, :, None] * ((w * d).sum(-1, keepdims=True) / length**2)
            f = scatter(d * coef, sa, sb, size).reshape(batch, n, 3)
            if nu is not None:
                rel = (vel[:, edges[:, 1]] - vel[:, edges[:, 0]]) * nu[None, :, None]
                f += scatter(rel, ea, eb, size).reshape(batch, n, 3)
            if kb or ka:
                fl = f.reshape(size, 3)
            if kb:
                sk = sum(kw[None, :, c, None] * pos[:, quads[:, c]] for c in range(4))
                sk = sk * (-kb * scale)[None, :, None]
                for c in range(4):
                    add_at(fl, hq[c], sk * kw[None, :, c, None])
            if ka:
                area_forces(pos, tri, corners, area0, ka, fl)
            acc = f * inv_w / mass + gravity[None, None] - (drag / mass) * vel
            vel = vel + h * acc
            if implicit:
                vel = damping_solve(vel * free + pin_v, pos, springs, b, sa, sb, weight * mass, h, implicit, free)
            pos = pos + h * vel
            pos = pos * free + target * pin
            vel = vel * free + pin_v
        out.append(pos.copy())
        if not np.isfinite(pos).all():
            return None
    return np.stack(out, 1)


def source_map(first, springs):
    """The source's own stiffness map on the springs: each vertex the mean `tri_stiffness` of its
    triangles, each spring the mean of its ends'."""
    if "tri_stiffness" not in first.files:
        raise SystemExit("--map source: the takes carry no tri_stiffness")
    tri = first["triangles"].astype(int)
    n = first["rest_uv"].shape[0]
    acc, count = np.zeros(n), np.zeros(n)
    for c in range(3):
        acc += np.bincount(tri[:, c], first["tri_stiffness"].astype(np.float64), n)
        count += np.bincount(tri[:, c], None, n)
    vertex = acc / np.maximum(count, 1)
    return 0.5 * (vertex[springs[:, 0]] + vertex[springs[:, 1]])


def diagonals_from_sides(values, springs, family):
    """`values` with each shear spring's (a cell's diagonal) replaced by the mean of its cell's
    sides' values over the sides' mean, times the diagonals' mean: one map for the cell."""
    side_of = {}
    for s in np.flatnonzero(family == 0):
        i, j = springs[s]
        side_of.setdefault(i, {})[j] = s
        side_of.setdefault(j, {})[i] = s
    rel = values / values[family == 0].mean()
    shear = np.flatnonzero(family == 1)
    shape = np.ones(len(shear))
    for n, s in enumerate(shear):
        i, j = springs[s]
        corners = set(side_of.get(i, {})) & set(side_of.get(j, {}))
        sides = [side_of[i][c] for c in corners] + [side_of[j][c] for c in corners]
        if sides:
            shape[n] = rel[sides].mean()
    out = values.copy()
    out[shear] = shape / shape.mean() * values[shear].mean()
    return out


def hinge_compression(k, shear, mesh_springs, kappa, c):
    """Each spring's stiffness in compression: `c k` on the shear springs (`shear`, a mask) that
    are no edge of the data's triangles (`mesh_springs`, the spring along each edge), `kappa k`
    on the other shear springs, `k` elsewhere."""
    on_mesh = np.zeros(len(k), dtype=bool)
    on_mesh[mesh_springs] = True
    return k * np.where(shear & ~on_mesh, c, np.where(shear, kappa, 1.0))


def compressions(a, k, shear, mesh_springs, kappa):
    """Each rollout's springs' stiffness in compression (None: as in tension) and how its line
    names it: one per value of `a.hinge_compression`, or of `a.compression` on
    `a.compression_on`'s springs (`diagonals`: the shear springs, `shear`, a mask); with
    neither, the run's own `kappa` (`sim.shear_compression`) on its shear springs, as the run
    steps."""
    if a.compression is None and a.hinge_compression is None:
        if kappa == 1.0:
            return [(None, "")]
        return [(k * np.where(shear, kappa, 1.0), f", the run's shear springs {kappa:g} in compression")]
    if a.hinge_compression is not None:
        return [(hinge_compression(k, shear, mesh_springs, kappa, c),
                 f", diagonals {kappa:g}, hinge diagonals {c:g} in compression")
                for c in (float(v) for v in a.hinge_compression.split(","))]
    rows = []
    for c in (float(v) for v in a.compression.split(",")):
        if c == 1.0:
            rows.append((None, ""))
            continue
        kc = k.copy()
        if a.compression_on == "edges":
            kc[mesh_springs] *= c
        elif a.compression_on == "diagonals":
            kc[shear] *= c
        else:
            kc *= c
        rows.append((kc, f", compression {c:g}"))
    return rows


def with_map(k, shape, family, share, families):
    """`k` with `share` of the map `shape` blended in per family (each family's map over its own
    mean), so each family's mean stiffness stays: `k (1 - share + share m / mean m)`."""
    out = k.copy()
    for f in families:
        sel = family == f
        out[sel] = k[sel] * (1.0 - share + share * shape[sel] / shape[sel].mean())
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("data")
    p.add_argument("--takes", type=int, default=1000, help="the first N takes of DATA")
    p.add_argument("--drag", type=float, help="sim.rayleigh, N*s/m (default: the run's)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--viscosity", type=float, help="one viscosity on every mesh edge, N*s/m")
    g.add_argument("--viscosity-source", type=float, metavar="SCALE",
                   help="the takes' own tri_kd, cotangent weights, times SCALE")
    g.add_argument("--viscosity-per-k", type=float, metavar="BETA",
                   help="on each edge BETA times the k of the spring along it (s)")
    p.add_argument("--project", action="store_true", help="the viscosity along the springs (into b)")
    p.add_argument("--uniform", help="K,B: one stiffness and damping on every spring")
    p.add_argument("--damping-per-k", type=float, metavar="BETA",
                   help="each spring's b = BETA * k (stiffness-proportional damping, s)")
    p.add_argument("--k-scale", type=float, default=1.0, help="every spring's k times this")
    p.add_argument("--shear-scale", default="1", metavar="S[,S...]",
                   help="the shear springs' k (a cell's diagonals, springs.npz family 1) times each S")
    p.add_argument("--substeps", type=int, help="substeps per frame (default: the run's)")
    p.add_argument("--implicit-damping", type=int, default=0, metavar="SWEEPS",
                   help="the springs' b by backward Euler, SWEEPS damped Jacobi sweeps per substep "
                   "(0: explicit, as springtime's step)")
    p.add_argument("--pins", choices=("linear", "cubic"), default="linear",
                   help="the pinned particles between frames: a straight line (springtime's step) or "
                   "the Catmull-Rom spline through the frames")
    p.add_argument("--bending", default="0", help="KB[,KB...]: a quadratic hinge bending stiffness (N m) "
                   "on every interior edge of the data's triangles, one rollout each")
    p.add_argument("--area", default="0", help="KA[,KA...]: an area term 1/2 KA (A - A0)^2 / A0 (N/m) "
                   "on every triangle, one rollout each (with each --bending)")
    p.add_argument("--compression", help="C[,C...]: the springs along the data's mesh edges "
                   "pull with k but push with C k when compressed (0: tension only), one rollout each "
                   "(default: the run's sim.shear_compression on its shear springs, as the run steps)")
    p.add_argument("--compression-on", choices=("edges", "diagonals", "all"), default="edges",
                   help="which springs --compression softens: the data's mesh edges, the cells' "
                   "diagonals (the run's shear springs, springs.npz family 1), every spring")
    p.add_argument("--hinge-compression", metavar="C[,C...]",
                   help="each cell's diagonal that is no edge of the data's triangles pushes with C k when "
                   "compressed, the other diagonals with the run's sim.shear_compression; one rollout each "
                   "(instead of --compression)")
    p.add_argument("--map", metavar="source|FILE",
                   help="a stiffness map to blend into the run's k: the takes' own (tri_stiffness) or "
                   "a springs .npz's k (e.g. the run's springs.learned.npz)")
    p.add_argument("--map-share", default="1", metavar="S[,S...]",
                   help="shares of --map blended in, one rollout each (each family keeps its mean k)")
    p.add_argument("--map-on", choices=("sides", "all"), default="all",
                   help="which springs --map shapes: the cells' sides, or the sides and diagonals")
    p.add_argument("--diagonals-from-sides", action="store_true",
                   help="each shear spring's (a cell's diagonal) k shaped by its cell's sides' instead of "
                   "its own (the diagonals' mean kept); with --map, the map's")
    a = p.parse_args()

    run = Path(a.run)
    config = (run / "config.toml").read_text()
    if a.substeps is not None and a.substeps < 1:
        raise SystemExit(f"--substeps: expected 1 or more, got {a.substeps}")
    if a.hinge_compression is not None and a.compression is not None:
        raise SystemExit("--hinge-compression and --compression: give one")
    if a.implicit_damping < 0:
        raise SystemExit(f"--implicit-damping: expected 0 (explicit) or more sweeps, got {a.implicit_damping}")
    substeps = a.substeps or int(re.search(r"^substeps\s*=\s*(\d+)", config, re.M).group(1))
    drag = a.drag if a.drag is not None else float(re.search(r"^rayleigh\s*=\s*(\S+)", config, re.M).group(1))
    net = np.load(run / "springs.npz")
    springs = net["springs"].astype(int)
    rest = net["rest_length"].astype(np.float64)
    if a.uniform:
        kk, bb = (float(v) for v in a.uniform.split(","))
        k, b = np.full(len(springs), kk), np.full(len(springs), bb)
    else:
        k, b = net["k"].astype(np.float64), net["b"].astype(np.float64)
    if a.damping_per_k is not None:
        b = a.damping_per_k * k
    k = k * a.k_scale

    first, x, pinned, dt = load_takes(a.data, a.takes)
    family = net["family"].astype(int)
    shape = None
    if a.map == "source":
        shape = source_map(first, springs)
    elif a.map:
        shape = np.load(a.map)["k"].astype(np.float64)
        if shape.shape != k.shape:
            raise SystemExit(f"--map {a.map}: {len(shape)} springs, the run has {len(k)}")
    if a.diagonals_from_sides:
        if shape is None:
            k = diagonals_from_sides(k, springs, family)
        else:
            shape = diagonals_from_sides(shape, springs, family)
    shares = [None] if shape is None else [float(v) for v in a.map_share.split(",")]
    map_families = (0,) if a.map_on == "sides" else (0, 1)
    k_run = k
    n = x.shape[2]
    mass = float(first["total_mass"]) / n
    weight = particle_weights(config, first, n)
    gravity = np.asarray(first["gravity"], dtype=np.float64)
    kd = None
    if a.viscosity_source is not None:
        if "tri_kd" not in first.files:
            raise SystemExit(f"{a.data}: the takes carry no tri_kd (only warp_cloth.py writes it)")
        kd = first["tri_kd"].astype(np.float64) * a.viscosity_source
    mesh, source_nu = mesh_edges(first["triangles"], first["rest_uv"].astype(np.float64), kd)
    index = {(min(i, j), max(i, j)): s for s, (i, j) in enumerate(springs)}
    mesh_springs = np.array([index[(i, j)] for i, j in mesh])  # the spring along each edge
    beta = float(re.search(r"^viscosity\s*=\s*(\S+)", config, re.M).group(1))

    def damping(k):
        """The viscosity's edges, `nu` and label, and the springs' `b`, for the stiffness `k`."""
        edges, spring_of = mesh, mesh_springs
        if kd is not None:
            nu, label = source_nu, f"source x {a.viscosity_source:g}"
        elif a.viscosity is not None:
            nu, label = np.full(len(edges), a.viscosity), f"{a.viscosity}"
        elif a.viscosity_per_k is not None:
            nu, label = a.viscosity_per_k * k[spring_of], f"{a.viscosity_per_k:g} k"
        elif beta > 0.0:
            # the run's own isotropic viscosity (`sim.viscosity`): beta k on every spring
            edges, spring_of = springs, np.arange(len(springs))
            nu, label = beta * k, f"the run's {beta:.3g} k"
        else:
            nu, label = None, "none"
        bb = b
        if nu is not None and a.project:
            bb = b.copy()
            np.add.at(bb, spring_of, nu)
            nu, label = None, label + " (projected)"
        return edges, nu, label, bb

    tri, uv = first["triangles"].astype(int), first["rest_uv"].astype(np.float64)
    hinge = hinge_stencils(tri, uv)
    area = (tri, triangle_areas(tri, uv))
    # the run's own stiffness in compression of its shear springs (1 in a config that predates it)
    found = re.search(r"^shear_compression\s*=\s*(\S+)", config, re.M)
    kappa = float(found.group(1)) if found else 1.0

    for share, shear in itertools.product(shares, (float(v) for v in a.shear_scale.split(","))):
        k = k_run if share is None else with_map(k_run, shape, family, share, map_families)
        k = np.where(family == 1, shear * k, k)
        a.share, a.shear = share, shear
        edges, nu, label, bb = damping(k)
        rows = compressions(a, k, family == 1, mesh_springs, kappa)
        for kb in (float(v) for v in a.bending.split(",")):
            for ka in (float(v) for v in a.area.split(",")):
                for kc, named in rows:
                    report(a, x, pinned, dt, substeps, springs, k, bb, rest, mass, weight, gravity, drag,
                           edges, nu, hinge, kb, area, ka, label, kc, named)

def report(a, x, pinned, dt, substeps, springs, k, b, rest, mass, weight, gravity, drag, edges, nu,
           hinge, kb, area, ka, label, kc=None, compression=""):
    start = time.time()
    sim = rollout(x, pinned, dt, substeps, springs, k, b, rest, mass, weight, gravity, drag, edges, nu,
                  hinge, kb, area, ka, kc, a.implicit_damping, a.pins)
    if sim is None:
        print(f"bending {kb:g}, area {ka:g}: diverged")
        return
    target = x[:, 1:]
    per = np.sqrt(((sim - target) ** 2).sum(-1).mean(-1))  # B, F
    t = np.arange(per.shape[1]) * dt
    windows = [per[:, (t > s - 1e-9) & (t <= s + 0.5 + 1e-9)].mean() for s in np.arange(0.0, t[-1], 0.5)]
    print(
        f"{len(x)} takes, drag {drag:.4g}, viscosity {label}, bending {kb:g}, area {ka:g}"
        + compression
        + (f", uniform {a.uniform}" if a.uniform else "")
        + (f", b = {a.damping_per_k:g} k" if a.damping_per_k is not None else "")
        + (f", {a.share:g} of the map {a.map} on {a.map_on}" if a.share is not None else "")
        + (", diagonals from sides" if a.diagonals_from_sides else "")
        + (f", shear springs' k x {a.shear:g}" if a.shear != 1.0 else "")
        + (f", b by backward Euler ({a.implicit_damping} sweeps)" if a.implicit_damping else "")
        + (f", pins {a.pins}" if a.pins != "linear" else "")
        + f": short {per[:, t <= SHORT + 1e-9].mean():.4f} m, long {per.mean():.4f} m; half seconds "
        + " ".join(f"{w:.3f}" for w in windows)
        + f" ({time.time() - start:.0f} s)"
    )


if __name__ == "__main__":
    main()
