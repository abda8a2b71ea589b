#!/usr/bin/env python3
"""blender_cloth: cloth rollouts from Blender's own cloth simulator for springtime to learn from.

A foreign source, not part of springtime: Blender run headless as a Python module (`bpy` from
PyPI). Each take builds a fresh scene: a res x res vertex grid ("subdivided plane") of side
`size` m lying flat and at rest in Blender's horizontal x-y plane (z up), with a Cloth modifier
(implicit mass-spring solver, collisions and self-collision off, gravity 9.81 m/s^2 along -Z).
A vertex group `stiffness` drives the cloth's structural (tension and compression) and shear
stiffness through `ClothSettings.vertex_group_structural_stiffness` and
`vertex_group_shear_stiffness`: weight 0 on a soft base, 1 on two vertical stripes, 0.5 on a band
along the top (v) edge. Blender gives every vertex `T(w) = tension_stiffness + w *
|tension_stiffness_max - tension_stiffness|` (the same for compression and shear) and every
spring the mean of its two ends' weights, so a stripe spring is 8x and a band spring 4.5x as
stiff as a base spring. 2-4 boundary vertices (weight 1 in the vertex group `pin`, the cloth's
`vertex_group_mass`, i.e. fully pinned) are carried by Hook modifiers (above the Cloth modifier)
to keyframed empties that follow smooth random paths for the first half of the take and are then
held; the rest of the sheet falls and swings from them.

The point cache is baked over the take, then every frame is written with Blender's own OBJ
exporter (`bpy.ops.wm.obj_export`, UVs on, default axes: y up, forward -Z, so Blender's (x, y,
z) is the file's (x, z, -y)) and the sequence is converted by `springtime import obj` (gravity
0,-9.81,0 in the file's axes). After the import each rollout gets the key `tri_stiffness`
(float32 [M], per triangle of its `triangles`: the mean of the three vertices' effective tension
stiffness T(w), in Blender's units) and `pin_indices`, `seed`, `tri_weight`; every other key is
kept. `OUT/source.json` records the simulator, bpy version, material, every parameter, the
quality (solver steps per frame), the seeds and the wall time.

Units. Blender's cloth counts time in frames and scales gravity by 0.001, so at time_scale 1 a
cloth falls at 9.81e-3 * fps^2 m/s^2 (5.65 at 24 fps). This script sets the cloth's `time_scale`
to sqrt(1000) / fps, which makes the fall exactly 9.81 m/s^2 with frame_dt = 1/fps; the solver's
time unit is then 1/sqrt(1000) s, so a spring of tension stiffness T pulls with 1000 * T * strain
newtons, and the air damping `air_damping` is a drag -c v on every vertex with c = air_damping *
0.01 * sqrt(1000) N s/m (passed to the importer as --rayleigh). The cloth's `mass` is per vertex;
it is set to 0.3 kg/m^2 * size^2 / res^2 (total mass = mass * vertices, passed as --mass), and all
force-like settings (stiffnesses and dampings) are the material's values, quoted for Blender's
default vertex mass of 0.3 kg, scaled by (vertex mass / 0.3): the same motion as a Blender user's
scene with the default mass and the quoted values.

Install and run (bpy wheels exist for the Python versions each Blender release supports; 5.0.1
installs on Python 3.11):

    python3 -m venv /work/venvs/bpy
    /work/venvs/bpy/bin/pip install bpy numpy
    /work/venvs/bpy/bin/python benches/foreign/blender_cloth.py OUT --train 16 --test 4 \\
        --seconds 4 --fps 24 --res 25 --size 3.0 --material soft --seed 0
    springtime data check OUT/train

The springtime binary is `--springtime PATH`, else `springtime` on PATH, else
target/release/springtime of this repository. OUT must be empty or new, or hold an earlier output
of this script (its source.json), which is then overwritten. The OBJ sequences are written under
OUT/obj/<split>/<take>/ and deleted after the import unless --keep-obj (--obj-only writes them
and stops, without springtime).
"""

import argparse
import math
import os
import shutil
import subprocess
import sys
import time

try:
    import numpy as np
except ImportError:
    sys.exit("blender_cloth.py needs numpy (and bpy): run it with the venv's python, see its docstring")

from foreign_common import (DENSITY, GRAVITY, PIN_MOTION, PinPath, add_common_args, check_common_args,
                            frame_count, grid_uv, pick_pins, prepare_out, stiffness_regions,
                            take_plan, write_source)

BLENDER_DEFAULT_MASS = 0.3  # kg per vertex: the material values below are quoted for this mass
# Weights of the stiffness vertex group: soft base 0, stripes 1, top band 0.5.
W_STRIPE = 1.0
W_BAND = 0.5

# Per material, in Blender's units for a vertex mass of 0.3 kg (Blender's default), scaled by
# (vertex mass / 0.3) when set: tension (= compression) stiffness at weight 0 and 1, shear
# stiffness at weight 0 and 1 (a third of tension, Blender's default ratio), bending stiffness
# (uniform), the dampings (Blender's defaults) and the quality (solver steps per frame). Soft: the
# base stretches a few % (mesh-edge strain RMS 1-3 % over a take, springs next to a pin far more);
# stiff: edge strain RMS 0.1-0.5 %, 99th percentile < 2 %. Quality 20 rather than Blender's 5: the
# implicit solver's numerical damping grows with the step (quality 5 vs 80 moved vertices by
# 0.11 m on average over a 2 s take, 20 vs 80 by 0.06 m), and 20 still bakes a 4 s take in 1.5-3 s.
MATERIALS = {
    "soft": dict(
        tension=2.0, tension_max=16.0, shear=2.0 / 3, shear_max=16.0 / 3, bending=0.05,
        tension_damping=5.0, shear_damping=5.0, bending_damping=0.5, air_damping=1.0, quality=20,
    ),
    "stiff": dict(
        tension=40.0, tension_max=320.0, shear=40.0 / 3, shear_max=320.0 / 3, bending=0.05,
        tension_damping=5.0, shear_damping=5.0, bending_damping=0.5, air_damping=1.0, quality=20,
    ),
}


def stiffness_weights(u, v, width, height):
    """Weight of the stiffness vertex group at rest coordinates (u, v): 0 on the soft base,
    W_STRIPE on two vertical stripes, W_BAND on a band along the top edge (the larger where
    they cross)."""
    stripe, band = stiffness_regions(u, v, width, height)
    return np.maximum(np.where(stripe, W_STRIPE, 0.0), np.where(band, W_BAND, 0.0))


# Blender's cloth settings and the key of `scaled_settings` each takes: compression follows
# tension, the bending stiffness is uniform (min = max).
CLOTH_SETTINGS = {
    "tension_stiffness": "tension", "tension_stiffness_max": "tension_max",
    "compression_stiffness": "tension", "compression_stiffness_max": "tension_max",
    "shear_stiffness": "shear", "shear_stiffness_max": "shear_max",
    "bending_stiffness": "bending", "bending_stiffness_max": "bending",
    "tension_damping": "tension_damping", "compression_damping": "tension_damping",
    "shear_damping": "shear_damping", "bending_damping": "bending_damping",
}


def scaled_settings(mat, vertex_mass):
    """The cloth settings as set: the material's force-like values times vertex_mass / 0.3."""
    f = vertex_mass / BLENDER_DEFAULT_MASS
    keys = ("tension", "tension_max", "shear", "shear_max", "bending",
            "tension_damping", "shear_damping", "bending_damping", "air_damping")
    return {k: mat[k] * f for k in keys}


def build_scene(bpy, args, mat, pins, path, frames):
    """A fresh scene with the cloth grid, its vertex groups, one hooked empty per pin and the
    Cloth modifier. Returns (cloth object, cloth modifier, settings record)."""
    res, size = args.res, args.size
    n = res * res
    cell = size / (res - 1)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = int(args.fps)
    scene.render.fps_base = 1.0
    scene.frame_start = 1
    scene.frame_end = frames  # take frame k is Blender frame k + 1
    scene.use_gravity = True
    scene.gravity = (0.0, 0.0, -GRAVITY)

    # the grid: vertex j * res + i at (i cell - size/2, j cell - size/2, 0), quads counterclockwise
    verts = [(i * cell - size / 2, j * cell - size / 2, 0.0) for j in range(res) for i in range(res)]
    faces = [(j * res + i, j * res + i + 1, (j + 1) * res + i + 1, (j + 1) * res + i)
             for j in range(res - 1) for i in range(res - 1)]
    mesh = bpy.data.meshes.new("cloth")
    mesh.from_pydata(verts, [], faces)
    mesh.validate()
    uv_layer = mesh.uv_layers.new(name="UVMap")
    uv = np.array([[(k % res) / (res - 1), (k // res) / (res - 1)] for k in range(n)])
    loop_verts = np.empty(len(mesh.loops), dtype=np.int32)
    mesh.loops.foreach_get("vertex_index", loop_verts)
    uv_layer.data.foreach_set("uv", uv[loop_verts].astype(np.float32).ravel())
    mesh.update()
    ob = bpy.data.objects.new("cloth", mesh)
    scene.collection.objects.link(ob)
    if len(mesh.vertices) != n:
        raise RuntimeError(f"the grid mesh has {len(mesh.vertices)} vertices, expected {n}")

    weights = stiffness_weights(uv[:, 0] * size, uv[:, 1] * size, size, size)
    vg_stiff = ob.vertex_groups.new(name="stiffness")
    for value in np.unique(weights):
        vg_stiff.add([int(k) for k in np.flatnonzero(weights == value)], float(value), "REPLACE")
    vg_pin = ob.vertex_groups.new(name="pin")
    vg_pin.add([int(k) for k in pins], 1.0, "REPLACE")

    # one empty per pin at the world origin, hooked to its vertex: the vertex moves by the empty's
    # location, keyed on every frame of the first half and held afterwards
    frame_dt = 1.0 / args.fps
    rest = np.array(verts)[pins]
    for p, vid in enumerate(pins):
        empty = bpy.data.objects.new(f"pin_{p}", None)
        scene.collection.objects.link(empty)
        hook = ob.modifiers.new(f"hook_{p}", "HOOK")
        hook.object = empty
        hook.vertex_indices_set([int(vid)])
        hook.falloff_type = "NONE"
        hook.strength = 1.0
    # linear keys (constant extrapolation, Blender's default, holds the last one)
    bpy.context.preferences.edit.keyframe_new_interpolation_type = "LINEAR"
    half = int(math.ceil(0.5 * args.seconds * args.fps))
    for k in range(0, min(half, frames - 1) + 1):
        target = path.position(k * frame_dt)
        for p in range(len(pins)):
            empty = bpy.data.objects[f"pin_{p}"]
            empty.location = tuple(target[p] - rest[p])
            empty.keyframe_insert("location", frame=k + 1)

    vertex_mass = DENSITY * size * size / n
    s = scaled_settings(mat, vertex_mass)
    cloth = ob.modifiers.new("Cloth", "CLOTH")  # after the hooks: the pins follow them
    cs = cloth.settings
    cs.quality = int(mat["quality"])
    cs.mass = vertex_mass
    cs.time_scale = math.sqrt(1000.0) / args.fps
    cs.air_damping = s["air_damping"]
    cs.bending_model = "ANGULAR"
    # min before max (the table's order): Blender keeps max >= min
    for name, key in CLOTH_SETTINGS.items():
        setattr(cs, name, s[key])
    cs.vertex_group_structural_stiffness = "stiffness"
    cs.vertex_group_shear_stiffness = "stiffness"
    cs.vertex_group_mass = "pin"
    cs.pin_stiffness = 1.0  # unused: weight-1 vertices are fully pinned
    cs.use_internal_springs = False
    cs.use_pressure = False
    cs.use_sewing_springs = False
    cs.use_dynamic_mesh = False
    cs.shrink_min = 0.0
    cs.shrink_max = 0.0
    cs.effector_weights.gravity = 1.0
    cloth.collision_settings.use_collision = False
    cloth.collision_settings.use_self_collision = False
    cloth.point_cache.frame_start = 1
    cloth.point_cache.frame_end = frames

    checks = {name: s[key] for name, key in CLOTH_SETTINGS.items() if name.endswith(("_stiffness", "_max"))}
    for name, want in checks.items():
        got = getattr(cs, name)
        if abs(got - want) > 1e-6 * max(1.0, abs(want)):
            raise RuntimeError(f"Blender set cloth.settings.{name} to {got}, asked for {want}")
    record = dict(
        quality=cs.quality, mass=cs.mass, time_scale=cs.time_scale, air_damping=cs.air_damping,
        **{name: getattr(cs, name) for name in CLOTH_SETTINGS},
        bending_model=cs.bending_model, pin_stiffness=cs.pin_stiffness,
        vertex_group_structural_stiffness=cs.vertex_group_structural_stiffness,
        vertex_group_shear_stiffness=cs.vertex_group_shear_stiffness,
        vertex_group_mass=cs.vertex_group_mass, use_collision=cloth.collision_settings.use_collision,
        use_self_collision=cloth.collision_settings.use_self_collision,
        gravity=list(scene.gravity), effector_gravity=cs.effector_weights.gravity,
    )
    return ob, cloth, weights, record


class quiet_stdout:
    """Send the C-level stdout (Blender's per-frame bake and export chatter) to /dev/null."""

    def __enter__(self):
        sys.stdout.flush()
        self.saved = os.dup(1)
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 1)
        os.close(null)

    def __exit__(self, *exc):
        sys.stdout.flush()
        os.dup2(self.saved, 1)
        os.close(self.saved)
        return False


def bake(bpy, scene, cloth):
    """Bake the cloth's point cache over the scene's frames (falls back to stepping through the
    frames, which fills the same cache, where the bake operator cannot run headless)."""
    try:
        with bpy.context.temp_override(scene=scene, point_cache=cloth.point_cache):
            result = bpy.ops.ptcache.bake(bake=True)
        if "FINISHED" in result and cloth.point_cache.is_baked:
            return "bpy.ops.ptcache.bake"
    except Exception as exc:  # noqa: BLE001 - report and fall back
        print(f"  ptcache.bake unavailable ({exc}); stepping through the frames", file=sys.stderr)
    for f in range(scene.frame_start, scene.frame_end + 1):
        scene.frame_set(f)
    return "frame_set over the take (in-memory cache)"


def export_frames(bpy, scene, ob, folder, frames):
    os.makedirs(folder, exist_ok=True)
    for obj in scene.objects:
        obj.select_set(obj == ob)
    bpy.context.view_layer.objects.active = ob
    for k in range(frames):
        scene.frame_set(k + 1)
        path = os.path.join(folder, f"frame_{k:04d}.obj")
        result = bpy.ops.wm.obj_export(
            filepath=path, export_selected_objects=True, export_uv=True, export_normals=False,
            export_materials=False, apply_modifiers=True, export_animation=False,
            forward_axis="NEGATIVE_Z", up_axis="Y",
        )
        if "FINISHED" not in result or not os.path.isfile(path):
            raise RuntimeError(f"Blender's OBJ exporter did not write {path} ({result})")


def read_obj_vertices(path):
    out = []
    with open(path) as fh:
        for line in fh:
            if line.startswith("v "):
                out.append([float(x) for x in line.split()[1:4]])
    return np.array(out)


def run_take(bpy, args, mat, seed, folder):
    """Simulate one take and write its OBJ frames into folder. Returns (take info, weights,
    settings record)."""
    rng = np.random.default_rng(seed)
    res, size = args.res, args.size
    n = res * res
    uv = grid_uv(res, size)
    pins = pick_pins(rng, res, size, uv)
    frames = frame_count(args)
    rest = np.column_stack([uv[:, 0] - size / 2, uv[:, 1] - size / 2, np.zeros(n)])
    path = PinPath(rng, rest[pins], size, 0.5 * args.seconds)
    ob, cloth, weights, record = build_scene(bpy, args, mat, pins, path, frames)
    t0 = time.time()
    with quiet_stdout():
        how = bake(bpy, bpy.context.scene, cloth)
    t_sim = time.time() - t0
    t0 = time.time()
    with quiet_stdout():
        export_frames(bpy, bpy.context.scene, ob, folder, frames)
    t_export = time.time() - t0

    # the exported frames: Blender (x, y, z) -> file (x, z, -y)
    to_file = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=float)
    first = read_obj_vertices(os.path.join(folder, "frame_0000.obj"))
    if first.shape != (n, 3) or np.abs(first - rest @ to_file.T).max() > 1e-4:
        raise RuntimeError("the first exported frame is not the rest grid in the expected vertex order/axes")
    k_half = int(math.ceil(0.5 * args.seconds * args.fps))
    probe = min(k_half, frames - 1)
    got = read_obj_vertices(os.path.join(folder, f"frame_{probe:04d}.obj"))[pins]
    want = path.position(probe / args.fps) @ to_file.T
    pin_err = float(np.abs(got - want).max())
    if not np.isfinite(got).all() or pin_err > 1e-3:
        raise RuntimeError(f"pinned vertices are {pin_err:.2e} m off their paths at frame {probe}")
    record["bake"] = how
    info = dict(seed=seed, pins=[int(p) for p in pins], frames=frames, sim_s=round(t_sim, 3),
                export_s=round(t_export, 3), pin_path_error_m=pin_err)
    return info, weights, record


def effective_tension(weights, record):
    """Blender's per-vertex tension stiffness: min + w * |max - min|."""
    lo, hi = record["tension_stiffness"], record["tension_stiffness_max"]
    return lo + weights * abs(hi - lo)


def find_springtime(arg):
    if arg:
        if not (os.path.isfile(arg) and os.access(arg, os.X_OK)):
            sys.exit(f"--springtime {arg}: no executable file there")
        return arg
    found = shutil.which("springtime")
    if found:
        return found
    here = os.path.dirname(os.path.abspath(__file__))
    local = os.path.normpath(os.path.join(here, "..", "..", "target", "release", "springtime"))
    if os.path.isfile(local) and os.access(local, os.X_OK):
        return local
    sys.exit(f"no springtime binary: none on PATH and none at {local}; build it (cargo build --release) "
             "or pass --springtime PATH (or use --obj-only)")


def import_take(springtime, folder, out_dir, args, total_mass, pins, rayleigh):
    cmd = [springtime, "import", "obj", folder, "--out", out_dir,
           "--frame-dt", repr(1.0 / args.fps), "--mass", repr(total_mass),
           "--pinned", ",".join(str(p) for p in pins),
           f"--gravity=0,{-GRAVITY},0", "--rayleigh", repr(rayleigh),
           "--width", repr(args.size), "--height", repr(args.size), "--force"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"springtime import failed ({proc.returncode}):\n  {' '.join(cmd)}\n{proc.stderr.strip()}")
    return cmd


def add_truth(npz_path, weights, record, info):
    data = dict(np.load(npz_path, allow_pickle=False))
    if "triangles" not in data:
        sys.exit(f"{npz_path} has no triangles: cannot attach tri_stiffness")
    tris = data["triangles"].astype(np.int64)
    vt = effective_tension(weights, record)
    data["tri_stiffness"] = vt[tris].mean(axis=1).astype(np.float32)
    data["tri_weight"] = weights[tris].mean(axis=1).astype(np.float32)
    data["pin_indices"] = np.array(info["pins"], dtype=np.int32)
    data["seed"] = np.int64(info["seed"])
    np.savez(npz_path, **data)
    return data


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_common_args(ap, MATERIALS, fps_type=int, fps_default=24, size_default=3.0, helps=dict(
        out="output folder (new, empty, or an earlier output of this script)",
        train="training takes (default 16)", test="test takes, other seeds (default 4)",
        seconds="length of a take, s (default 4)", fps="frames per second (default 24)",
        res="vertices per side (default 25)", size="side of the sheet, m (default 3)"))
    ap.add_argument("--springtime", metavar="PATH", help="the springtime binary")
    ap.add_argument("--keep-obj", action="store_true", help="keep the OBJ sequences under OUT/obj")
    ap.add_argument("--obj-only", action="store_true",
                    help="write the OBJ sequences only (no import, no springtime needed)")
    args = ap.parse_args()
    check_common_args(ap, args, 1, 240)
    if args.train < 0 or args.test < 0 or args.train + args.test == 0:
        ap.error("need --train >= 0, --test >= 0 and at least one take")
    springtime = None if args.obj_only else find_springtime(args.springtime)
    try:
        import bpy
    except ImportError as exc:
        sys.exit(f"cannot import bpy ({exc}): run this with a Python that has `pip install bpy`")
    prepare_out(args.out, __file__, ("train", "test", "obj"))

    mat = MATERIALS[args.material]
    frames = frame_count(args)
    n = args.res * args.res
    vertex_mass = DENSITY * args.size**2 / n
    total_mass = vertex_mass * n
    rayleigh = None
    start = time.time()
    takes, record, import_cmd = [], None, None
    for split, i, seed in take_plan(args):
        name = f"take_{i:03d}"
        folder = os.path.join(args.out, "obj", split, name)
        t0 = time.time()
        info, weights, record = run_take(bpy, args, mat, seed, folder)
        rayleigh = record["air_damping"] * 0.01 * math.sqrt(1000.0)
        if not args.obj_only:
            import_cmd = import_take(springtime, folder, os.path.join(args.out, split), args,
                                     total_mass, info["pins"], rayleigh)
            add_truth(os.path.join(args.out, split, f"{name}.npz"), weights, record, info)
            if not args.keep_obj:
                shutil.rmtree(folder)
        info.update(split=split, index=i, name=name, seconds=round(time.time() - t0, 3))
        takes.append(info)
        print(f"{split}/{name}: {len(info['pins'])} pins, {info['seconds']:.1f} s "
              f"(bake {info['sim_s']:.1f} s, export {info['export_s']:.1f} s)", flush=True)
    if not args.obj_only and not args.keep_obj:
        shutil.rmtree(os.path.join(args.out, "obj"), ignore_errors=True)
    wall = time.time() - start
    s = scaled_settings(mat, vertex_mass)
    write_source(
        args, takes, wall,
        simulator="blender",
        package="bpy",
        version=bpy.app.version_string,
        device=None,
        description="Blender cloth modifier (implicit mass-spring solver), run headless through bpy; "
                    "frames written by bpy.ops.wm.obj_export, converted by springtime import obj",
        material_values_at_vertex_mass_0_3=mat,
        cloth_settings=record,
        parameters=dict(
            res=args.res, size_m=args.size, vertices=n, density_kg_m2=DENSITY,
            vertex_mass_kg=vertex_mass, total_mass_kg=total_mass, force_scale=vertex_mass / BLENDER_DEFAULT_MASS,
            gravity_file_axes_m_s2=[0.0, -GRAVITY, 0.0], gravity_blender_axes_m_s2=[0.0, 0.0, -GRAVITY],
            time_scale=math.sqrt(1000.0) / args.fps,
            time_scale_rule="sqrt(1000)/fps: Blender's cloth steps in frames and scales gravity by 0.001, "
                            "so this makes the fall 9.81 m/s^2 with frame_dt = 1/fps",
            spring_force_rule="force = 1000 * T * strain N for a spring of tension stiffness T "
                              "(k = T / mean structural spring length in Blender's solver units)",
            rayleigh_N_s_m=rayleigh,
            rayleigh_rule="air drag -c v per vertex, c = air_damping * 0.01 * sqrt(1000) N s/m",
            tension_stiffness_base=s["tension"], tension_stiffness_max=s["tension_max"],
            stiffness_map="vertex group 'stiffness' (structural and shear): weight 1 where |u-0.3W|<0.08W or "
                          "|u-0.7W|<0.08W (stripes), 0.5 where v>0.85H (top band, stripes win), 0 elsewhere",
            stiffness_rule="per vertex T(w) = tension_stiffness + w*|tension_stiffness_max - tension_stiffness| "
                           "(same for compression and shear); per spring the mean of its ends' T(w); "
                           "tri_stiffness = mean of a triangle's three vertices' T(w)",
            map_ratio_stripe=(s["tension"] + W_STRIPE * (s["tension_max"] - s["tension"])) / s["tension"],
            map_ratio_band=(s["tension"] + W_BAND * (s["tension_max"] - s["tension"])) / s["tension"],
            pins="2-4 boundary vertices >= 0.25 size apart, weight 1 in vertex_group_mass (fully pinned), "
                 f"each hooked to an empty keyed every frame: {PIN_MOTION}",
            start="flat, at rest, horizontal (Blender x-y plane; file x-z plane), falls under gravity; "
                  "no collisions, no self-collision",
            obj_export="bpy.ops.wm.obj_export per frame: export_uv, no normals/materials, apply_modifiers, "
                       "forward -Z, up Y (file = Blender (x, z, -y))",
        ),
        fps=args.fps,
        frame_dt_s=1.0 / args.fps,
        seconds=args.seconds,
        frames=frames,
        quality_steps_per_frame=mat["quality"],
        import_command_example=import_cmd,
    )


if __name__ == "__main__":
    main()
