#!/usr/bin/env python3
"""tpcloth: an independent cloth simulator that writes rollouts the way a user's tool would.

It shares no code and few conventions with springtime, on purpose: springtime must learn from
data it did not generate itself. What differs from springtime's own sources:

- code base: Python + NumPy, written from the textbook formulas, not from springtime's Rust;
- mesh: an irregular triangulation (interior vertices jittered, each cell split along a random
  diagonal), so landmarks lie on no grid;
- membrane: compressible neo-Hookean (plane stress Lamé parameters from a per-triangle Young's
  modulus), not co-rotational / StVK, and no strain-rate damping;
- bending: a quadratic hinge energy (Bergou-style, linear forces), not dihedral angles;
- damping: dashpots along every mesh edge plus mass-proportional air drag (per unit mass),
  not Rayleigh damping of a uniform mass;
- masses: one third of each adjacent triangle's area (boundary vertices are lighter);
- time stepping: classical RK4 at a step derived from the stiffest element, not semi-implicit
  Euler; frames stored at camera rate (30 fps by default) with no velocities;
- pins and excitation: two boundary vertices (or, with --pin-radius, the vertices within that
  radius of each: a clamp), chosen at random per rollout, shaken along smooth random paths for
  part of the rollout and then held;
- files: `np.savez_compressed`, float64 positions, extra metadata keys of every kind (strings,
  a pickled dict, float16 and int8 arrays), the gravity vector and drag stored with their own
  names.

Usage: python3 tpcloth.py OUT_DIR [--rollouts N] [--test N] [--res R] [--size M] ...
Writes OUT_DIR/train/rollout_XXX.npz and OUT_DIR/test/rollout_XXX.npz plus OUT_DIR/tpcloth.json
(the parameters, including the per-triangle Young's modulus map as `tri_stiffness` in each file).
"""

import argparse
import json
import os
import sys
import time

import numpy as np


def make_mesh(res, size, jitter, rng):
    """Vertices (rest, 2-D), triangles of an irregular triangulation of a size x size square."""
    h = size / (res - 1)
    u, v = np.meshgrid(np.linspace(0.0, size, res), np.linspace(0.0, size, res), indexing="xy")
    rest = np.stack([u.ravel(), v.ravel()], axis=1)
    interior = np.ones((res, res), bool)
    interior[0, :] = interior[-1, :] = interior[:, 0] = interior[:, -1] = False
    interior = interior.ravel()
    rest[interior] += rng.uniform(-jitter * h, jitter * h, size=(interior.sum(), 2))
    tris = []
    for j in range(res - 1):
        for i in range(res - 1):
            a = j * res + i
            b, c, d = a + 1, a + res, a + res + 1
            if rng.random() < 0.5:
                tris += [(a, b, d), (a, d, c)]
            else:
                tris += [(a, b, c), (b, d, c)]
    return rest, np.array(tris, dtype=np.int64)


def stiffness_map(rest_tri_centres, size, levels, layout):
    """Young's modulus per triangle (N/m): a soft base, two stiff vertical stripes, a stiff top
    band and a middle patch (like the paper's Fig. 10 (a))."""
    soft, mid, stiff = levels
    x, y = rest_tri_centres[:, 0] / size, rest_tri_centres[:, 1] / size
    e = np.full(len(x), soft)
    if layout == "uniform":
        return np.full(len(x), mid)
    e[((x > 0.15) & (x < 0.3)) | ((x > 0.7) & (x < 0.85))] = stiff
    e[y > 0.8] = stiff
    e[(x > 0.4) & (x < 0.6) & (y > 0.35) & (y < 0.6)] = mid
    return e


def scatter_add(out, idx, vals):
    """out[:, idx] += vals for out [R, N, 3], idx [K], vals [R, K, 3] (np.bincount: fast)."""
    r, n, _ = out.shape
    flat = (np.arange(r)[:, None] * n + idx[None, :]).ravel()
    for c in range(3):
        out[..., c] += np.bincount(flat, weights=vals[..., c].ravel(), minlength=r * n).reshape(r, n)


class Cloth:
    def __init__(self, rest, tris, young, poisson, density, bend, edge_damping, drag):
        self.rest, self.tris = rest, tris
        p0, p1, p2 = rest[tris[:, 0]], rest[tris[:, 1]], rest[tris[:, 2]]
        dm = np.stack([p1 - p0, p2 - p0], axis=2)  # [M, 2, 2]
        self.area = 0.5 * np.abs(np.linalg.det(dm))
        self.dm_inv = np.linalg.inv(dm)
        self.mu = young / (2.0 * (1.0 + poisson))
        self.lam = young * poisson / (1.0 - poisson**2)  # plane stress
        n = len(rest)
        self.mass = np.zeros(n)
        for k in range(3):
            np.add.at(self.mass, tris[:, k], density * self.area / 3.0)
        # unique edges
        e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
        e = np.unique(np.sort(e, axis=1), axis=0)
        self.edges = e
        # quadratic bending (Bergou et al. 2006 in spirit): per interior edge, the four weights w
        # with sum w = 0 and sum w p = 0 over the flat rest positions p, so sum w x vanishes on
        # every planar (affine) configuration; energy bend/2 * A_e * |sum w x|^2, linear forces.
        owner = {}
        for ti, tri in enumerate(tris):
            for k in range(3):
                a, b = sorted((tri[k], tri[(k + 1) % 3]))
                owner.setdefault((a, b), []).append(tri[(k + 2) % 3])
        hinges, weights = [], []
        for (a, b), opp in owner.items():
            if len(opp) != 2:
                continue
            idx = [a, b, opp[0], opp[1]]
            m = np.vstack([rest[idx].T, np.ones(4)])  # 3 x 4
            w = np.linalg.svd(m)[2][-1]
            le2 = np.sum((rest[a] - rest[b]) ** 2)
            w = w / np.max(np.abs(w)) / le2
            hinges.append(idx)
            weights.append(w)
        self.hinges = np.array(hinges)
        self.hinge_w = np.array(weights)
        # hinge area: a third of the two adjacent triangles, approximated by the edge length squared
        self.hinge_coef = bend * np.array([np.sum((rest[h[0]] - rest[h[1]]) ** 2) for h in hinges])
        self.edge_damping = edge_damping
        self.drag = drag
        self.young = young

    def forces(self, x, v, gravity):
        """Net force [R, N, 3] on states x, v of shape [R, N, 3]."""
        t = self.tris
        x0, x1, x2 = x[:, t[:, 0]], x[:, t[:, 1]], x[:, t[:, 2]]
        ds = np.stack([x1 - x0, x2 - x0], axis=3)  # [R, M, 3, 2]
        f = ds @ self.dm_inv[None]  # deformation gradient, [R, M, 3, 2]
        ftf = np.swapaxes(f, 2, 3) @ f  # [R, M, 2, 2]
        det = ftf[..., 0, 0] * ftf[..., 1, 1] - ftf[..., 0, 1] * ftf[..., 1, 0]
        det = np.maximum(det, 1e-12)
        j = np.sqrt(det)
        inv = np.empty_like(ftf)
        inv[..., 0, 0] = ftf[..., 1, 1] / det
        inv[..., 1, 1] = ftf[..., 0, 0] / det
        inv[..., 0, 1] = -ftf[..., 0, 1] / det
        inv[..., 1, 0] = -ftf[..., 1, 0] / det
        mu = self.mu[None, :, None, None]
        lam = self.lam[None, :, None, None]
        pk1 = mu * f + (lam * np.log(j)[..., None, None] - mu) * (f @ inv)
        hmat = -self.area[None, :, None, None] * (pk1 @ np.swapaxes(self.dm_inv, 1, 2)[None])
        fa, fb = hmat[..., 0], hmat[..., 1]
        out = np.zeros_like(x)
        scatter_add(out, t[:, 1], fa)
        scatter_add(out, t[:, 2], fb)
        scatter_add(out, t[:, 0], -fa - fb)
        kx = np.einsum("hi,rhik->rhk", self.hinge_w, x[:, self.hinges])  # [R, H, 3]
        g = (self.hinge_coef[None, :, None] * kx)[:, :, None, :] * self.hinge_w[None, :, :, None]
        for k in range(4):
            scatter_add(out, self.hinges[:, k], -g[:, :, k])
        e = self.edges
        d = x[:, e[:, 1]] - x[:, e[:, 0]]
        d /= np.linalg.norm(d, axis=2, keepdims=True) + 1e-12
        rel = np.sum((v[:, e[:, 1]] - v[:, e[:, 0]]) * d, axis=2, keepdims=True)
        fd = self.edge_damping * rel * d
        scatter_add(out, e[:, 0], fd)
        scatter_add(out, e[:, 1], -fd)
        m = self.mass[None, :, None]
        out += m * (np.asarray(gravity)[None, None, :] - self.drag * v)
        return out

    def stable_dt(self):
        """RK4 step from the stiffest element: dt * omega_max <= 2 (RK4 is stable to 2.78)."""
        omega2 = 8.0 * np.max(self.young) / np.min(self.mass)
        bend = np.max(self.hinge_coef * np.sum(self.hinge_w**2, axis=1))
        omega2 += 4.0 * bend / np.min(self.mass)
        return 2.0 / np.sqrt(omega2)


def pin_paths(rng, t, shake_seconds):
    """Offsets of the two anchors from their rest positions at times `t`, [len(t), 2, 3]: smooth
    random shaking that starts and ends at rest (a sum of sines under a sin(pi t / T) envelope)."""
    out = np.zeros((len(t), 2, 3))
    ramp = np.clip(t / shake_seconds, 0, 1)
    envelope = np.sin(np.pi * ramp) * (t <= shake_seconds)
    for p in range(2):
        for axis in range(3):
            for _ in range(3):
                amp = rng.uniform(0.0, 0.15) * (1.5 if axis == 2 else 1.0)
                freq = rng.uniform(0.2, 1.5)
                phase = rng.uniform(0, 2 * np.pi)
                out[:, p, axis] += amp * envelope * np.sin(2 * np.pi * freq * t + phase)
    return out


def rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    a, b, c, d = q
    return np.array([
        [a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
        [2 * (b * c + a * d), a * a - b * b + c * c - d * d, 2 * (c * d - a * b)],
        [2 * (b * d - a * c), 2 * (c * d + a * b), a * a - b * b - c * c + d * d],
    ])


def simulate(cloth, rng, n, seconds, fps, substeps, gravity, shake_seconds, pin_radius):
    """n rollouts at once; returns positions [n, F, V, 3] and the pinned masks [n, V].

    Each rollout holds the sheet by two anchors: boundary vertices chosen at random (at least
    0.4 of the sheet apart), each with every vertex within `pin_radius` of it in the rest sheet
    (0: the single vertex), moved rigidly along its anchor's path."""
    res_v = len(cloth.rest)
    frames = int(round(seconds * fps)) + 1
    boundary = np.where(
        (cloth.rest[:, 0] <= 1e-9) | (cloth.rest[:, 1] <= 1e-9)
        | (cloth.rest[:, 0] >= cloth.rest[:, 0].max() - 1e-9)
        | (cloth.rest[:, 1] >= cloth.rest[:, 1].max() - 1e-9)
    )[0]
    x = np.zeros((n, res_v, 3))
    anchor = np.full((n, res_v), -1)  # which anchor holds each vertex (-1: free)
    offsets = []
    # sampled at every substep (and half substep, for RK4's midpoints): smooth driving
    fine = np.arange(0, (frames - 1) * substeps * 2 + 1) / (fps * substeps * 2)
    for r in range(n):
        pair = rng.choice(boundary, size=2, replace=False)
        while np.linalg.norm(cloth.rest[pair[0]] - cloth.rest[pair[1]]) < 0.4 * cloth.rest.max():
            pair = rng.choice(boundary, size=2, replace=False)
        for a, v in enumerate(pair):
            near = np.linalg.norm(cloth.rest - cloth.rest[v], axis=1) <= pin_radius
            near[v] = True
            anchor[r, near] = a
        rest3 = np.concatenate([cloth.rest, np.zeros((res_v, 1))], axis=1)
        rest3 = rest3 - rest3[pair].mean(axis=0)
        rest3 = rest3 @ rotation(rng).T
        x[r] = rest3
        offsets.append(pin_paths(rng, fine, shake_seconds))
    offsets = np.array(offsets)  # [n, 2 * substeps * (F - 1) + 1, 2, 3], half-substep samples
    pinned = anchor >= 0
    held = np.where(pinned)  # (rollout, vertex) pairs
    which = anchor[held]
    base = x[held]  # rest positions of the held vertices
    v = np.zeros_like(x)
    out = np.zeros((n, frames, res_v, 3))
    out[:, 0] = x
    dt = 1.0 / (fps * substeps)
    free = (~pinned)[..., None].astype(float)
    inv_m = 1.0 / cloth.mass[None, :, None]

    def accel(x, v):
        return cloth.forces(x, v, gravity) * inv_m * free

    h = 0.5 * dt

    def pin_state(k):
        """Held positions and velocities at half-substep sample k."""
        k0, k1 = max(k - 1, 0), min(k + 1, offsets.shape[1] - 1)
        px = base + offsets[held[0], k, which]
        pv = (offsets[held[0], k1, which] - offsets[held[0], k0, which]) / ((k1 - k0) * h)
        return px, pv

    def accel_at(x, v, k):
        px, pv = pin_state(k)
        x = x.copy(); v = v.copy()
        x[held] = px
        v[held] = pv
        return accel(x, v), v

    for f in range(1, frames):
        for s in range(substeps):
            k = 2 * ((f - 1) * substeps + s)  # half-substep index of the step's start
            k1v, k1x = accel_at(x, v, k)
            k2v, k2x = accel_at(x + 0.5 * dt * k1x, v + 0.5 * dt * k1v, k + 1)
            k3v, k3x = accel_at(x + 0.5 * dt * k2x, v + 0.5 * dt * k2v, k + 1)
            k4v, k4x = accel_at(x + dt * k3x, v + dt * k3v, k + 2)
            x = x + dt / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x)
            v = v + dt / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
            px, pv = pin_state(k + 2)
            x[held] = px
            v[held] = pv
        if not np.all(np.isfinite(x)):
            sys.exit(f"tpcloth: the simulation diverged at frame {f}; lower --young or raise --substeps")
        out[:, f] = x
    return out, pinned


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out")
    ap.add_argument("--rollouts", type=int, default=32)
    ap.add_argument("--test", type=int, default=8)
    ap.add_argument("--res", type=int, default=21, help="vertices per side")
    ap.add_argument("--size", type=float, default=2.0, help="sheet side, m")
    ap.add_argument("--density", type=float, default=0.25, help="kg/m^2")
    ap.add_argument("--young", type=float, nargs=3, default=[200.0, 600.0, 2000.0], help="soft mid stiff, N/m")
    ap.add_argument("--layout", default="patches", choices=["patches", "uniform"])
    ap.add_argument("--poisson", type=float, default=0.3)
    ap.add_argument("--bend", type=float, default=1e-3, help="bending stiffness, N m")
    ap.add_argument("--edge-damping", type=float, default=0.15, help="edge dashpots, N s/m")
    ap.add_argument("--drag", type=float, default=0.3, help="air drag per unit mass, 1/s")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--substeps", type=int, default=0, help="RK4 steps per frame (0: from the stiffest element)")
    ap.add_argument("--shake", type=float, default=2.5, help="seconds of pin shaking")
    ap.add_argument("--pin-radius", type=float, default=0.0,
                    help="anchor radius in the rest sheet, m (0: two single vertices)")
    ap.add_argument("--jitter", type=float, default=0.25, help="interior vertex jitter, fraction of spacing")
    ap.add_argument("--velocities", action="store_true", help="also store velocities (central differences)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--rollout-seed", type=int, default=None,
                    help="seed of the rollouts alone (default: --seed); the mesh and map keep --seed, so "
                    "a second process can write more rollouts of the same cloth, e.g. the test split")
    ap.add_argument("--perturb", type=float, default=0.0,
                    help="the chaos floor: multiply each triangle's Young's modulus by 1 + this x N(0, 1) "
                    "(seeded by --perturb-seed; the substeps and the rollouts' seeds stay those of the "
                    "unperturbed cloth, so the rollouts differ only by the perturbation)")
    ap.add_argument("--perturb-seed", type=int, default=1)
    a = ap.parse_args()

    rng = np.random.default_rng(a.seed)
    rest, tris = make_mesh(a.res, a.size, a.jitter, rng)
    centres = rest[tris].mean(axis=1)
    young = stiffness_map(centres, a.size, a.young, a.layout)
    if a.rollout_seed is not None:
        rng = np.random.default_rng(a.rollout_seed)
    gravity = np.array([0.0, 0.0, -9.81])
    cloth = Cloth(rest, tris, young, a.poisson, a.density, a.bend, a.edge_damping, a.drag)
    substeps = a.substeps or int(np.ceil(1.0 / (a.fps * cloth.stable_dt())))
    if a.perturb:
        factor = 1.0 + a.perturb * np.random.default_rng(a.perturb_seed).normal(size=len(young))
        young = young * factor
        cloth = Cloth(rest, tris, young, a.poisson, a.density, a.bend, a.edge_damping, a.drag)
    os.makedirs(a.out, exist_ok=True)
    total = 0
    t0 = time.time()
    for split, count in (("train", a.rollouts), ("test", a.test)):
        if count == 0:
            continue
        pos, pinned_all = simulate(cloth, rng, count, a.seconds, a.fps, substeps, gravity, a.shake,
                                   a.pin_radius)
        print(f"tpcloth: simulated {count} {split} rollouts ({time.time() - t0:.1f} s)", flush=True)
        for r in range(count):
            pinned = pinned_all[r]
            data = dict(
                positions=pos[r],  # float64 on purpose
                rest_uv=rest,
                pinned=pinned,
                frame_dt=np.float64(1.0 / a.fps),
                total_mass=np.float64(cloth.mass.sum()),
                width=np.float64(a.size),
                height=np.float64(a.size),
                triangles=tris.astype(np.int32),
                tri_stiffness=young.astype(np.float32),
                gravity=gravity,
                # metadata a real tool writes, which springtime must ignore
                simulator=np.array("tpcloth 0.3 (RK4, neo-Hookean)"),
                units=np.array("meters"),
                fps=np.int64(round(a.fps)),
                vertex_mass=cloth.mass.astype(np.float16),
                material=np.array({"poisson": a.poisson, "drag_per_mass": a.drag}, dtype=object),
                flags=np.zeros(len(rest), np.int8),
                air_drag_per_mass=np.float64(a.drag),
            )
            if a.velocities:
                vel = np.gradient(pos[r], 1.0 / a.fps, axis=0)
                data["velocities"] = vel.astype(np.float32)
            os.makedirs(os.path.join(a.out, split), exist_ok=True)
            np.savez_compressed(os.path.join(a.out, split, f"rollout_{r:03d}.npz"), **data)
            total += 1
    with open(os.path.join(a.out, "tpcloth.json"), "w") as fh:
        json.dump({**vars(a), "substeps_used": substeps, "vertices": len(rest), "triangles": len(tris),
                   "total_mass": float(cloth.mass.sum()), "seconds_wall": time.time() - t0,
                   "numpy": np.__version__}, fh, indent=1)
    print(f"tpcloth: wrote {total} rollouts to {a.out} ({substeps} RK4 steps per frame, {time.time() - t0:.1f} s)")


if __name__ == "__main__":
    main()
