#!/usr/bin/env python3
"""The cross-simulator bench: springtime's recipe for other simulators' data on takes from
simulators nobody on the team wrote.

One command generates (once) takes from every simulator of the bench, trains
`configs/thirdparty_mesh.toml` (the book's one recipe for other simulators' data) on each
set's training takes, evaluates it on the held-out test takes beside the best uniform network
(`eval.uniform_baseline`), and prints the table: motion RMSE of the trained surrogate and of the
best uniform network at the short horizon (0.8 s) and over the whole take, the gain, the
gain over the best bending-apart network (uniform, its bending springs sized apart), the gain
over the best uniform network with its own drag and viscosity, the Spearman correlation of the learned structural `k` with the source's stiffness map, the
surrogate's substeps and the training's wall time.

    python3 benches/foreign/run.py                      # every simulator, soft and stiff
    python3 benches/foreign/run.py --sims mujoco,warp --materials soft --quick
    python3 benches/foreign/run.py --set train.scale_search=false --tag noscale
    python3 benches/foreign/run.py --capture 0.002,0.1 --tag capture   # capture-grade tracks
                                 # (the copies state their noise: `position_noise`)
    python3 benches/foreign/run.py --source-map             # + what the source's own map wins
    python3 benches/foreign/run.py --sims warp,newton --spread 0.01   # + the source's own spread
    python3 benches/foreign/run.py --sims newton --materials soft \
        --variant "fps30=--fps 30 --res 21 --size 1.5 --seed 11"  # another configuration

`--source-map` runs `springtime diagnose` on each finished run and adds its source-map
reference to the table: the source's own stiffness map on the structural springs, sized on the
training takes, against the best uniform network at its step on the test takes — what a
perfectly ranked map wins with this surrogate (the book, "What the source's own map is worth").

`--spread EPS` re-runs each set's test takes with every triangle's material times
`1 + EPS·N(0, 1)` (the generators' `--perturb`; all but Blender) and adds how far they land
from the originals, as `eval` measures (`takes_rmse.py`), to the table: the source's own spread,
how far the source misses its own takes with its material EPS off. A surrogate is not
expected to come closer than that; where the spread is near the best uniform network's error,
no gain at that horizon is to be had from the map.

Each simulator runs in a virtual environment of its own, made on first use under
`--venvs` (default `~/.cache/springtime-foreign`) from PyPI with the pinned packages below;
the data goes to `--out`/data/<sim>-<material>/ (generated once, reused while its
`source.json` records the same arguments), the runs to `--out`/runs/<tag>/<sim>-<material>/,
the table to `--out`/bench-<tag>.md and `.json`. Needs the springtime binary (`cargo build
--release`; `--springtime PATH` to use another). Standard library only.
"""

import argparse
import json
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent

# numpy is pinned too (since 2026-12-05): tpcloth is NumPy alone, and its takes, regenerated in
# an environment with another numpy, part from the earlier ones over a take as a chaotic cloth's
# do (the book, Results → Other simulators). bpy 5.0.1 installs its own numpy 1.26.4.
# Each simulator: its generator, the packages of its environment, and the generator's arguments
# per material (besides OUT and the split sizes). The four external generators share one
# command line: OUT --train N --test M --seconds S --material soft|stiff --seed X.
SIMS = {
    "blender": {
        "script": HERE / "blender_cloth.py",
        "packages": ["bpy==5.0.1", "numpy==1.26.4"],
        "springtime": True,
    },
    "warp": {
        "script": HERE / "warp_cloth.py",
        "packages": ["warp-lang==1.7.2", "numpy==2.4.6"],
        # --spread: the arguments that re-run the set's test takes with the material perturbed by
        # EPS (appended; the last --train/--perturb win)
        "perturb": ["--train", "0", "--perturb"],
    },
    "newton": {
        "script": HERE / "newton_cloth.py",
        "packages": ["newton==1.8.0", "numpy==2.4.6"],
        # VBD at 25 x 25 costs ~2 min per stiff 4-s take on two cores: a coarser sheet.
        "extra": ["--res", "17"],
        "perturb": ["--train", "0", "--perturb"],
    },
    "mujoco": {
        "script": HERE / "mujoco_cloth.py",
        "packages": ["mujoco==4.0.0", "numpy==2.4.6"],
        "perturb": ["--train", "0", "--perturb"],
    },
    # The team's own independent NumPy simulator (tests/thirdparty/tpcloth.py): a jittered
    # irregular mesh, neo-Hookean membrane, RK4; not a tool users have, kept as the reference.
    "tpcloth": {
        "script": ROOT / "tests" / "thirdparty" / "tpcloth.py",
        "packages": ["numpy==2.4.6"],
        # one random stream for all its rollouts: the training takes are made again too
        "perturb": ["--perturb"],
        "args": {
            "soft": ["--res", "17", "--size", "2", "--young", "66", "266", "666", "--fps", "50",
                     "--pin-radius", "0.2"],
            "stiff": ["--res", "17", "--size", "2", "--young", "330", "1330", "3330", "--fps",
                      "50", "--pin-radius", "0.2"],
        },
    },
}


def die(msg):
    print(f"error: {msg}", file=sys.stderr)
    sys.exit(1)


def venv_python(venvs: Path, sim: str) -> Path:
    """The simulator's environment, made on first use."""
    spec = SIMS[sim]
    env = venvs / f"venv-{sim}"
    py = env / "bin" / "python"
    stamp = env / "springtime-packages.txt"
    want = "\n".join(spec["packages"])
    if py.exists() and stamp.exists() and stamp.read_text().strip() == want:
        return py
    print(f"[{sim}] making {env} with {' '.join(spec['packages'])}", flush=True)
    shutil.rmtree(env, ignore_errors=True)
    subprocess.run([sys.executable, "-m", "venv", str(env)], check=True)
    subprocess.run([str(py), "-m", "pip", "install", "-q", *spec["packages"]], check=True)
    stamp.write_text(want)
    return py


def generator_args(sim, material, a):
    spec = SIMS[sim]
    if sim == "tpcloth":
        return ["--rollouts", str(a.train), "--test", str(a.test), "--seconds", str(a.seconds),
                "--seed", str(a.seed), *spec["args"][material], *a.variant_args]
    args = ["--train", str(a.train), "--test", str(a.test), "--seconds", str(a.seconds),
            "--material", material, "--seed", str(a.seed), *spec.get("extra", []),
            *a.variant_args]
    if spec.get("springtime"):
        args += ["--springtime", str(a.springtime)]
    return args


def set_name(sim, material, a) -> str:
    """A set's name: `<sim>-<material>`, and `-<variant>` for another configuration."""
    return f"{sim}-{material}" + (f"-{a.variant_name}" if a.variant_name else "")


def same_takes(recorded, args) -> bool:
    """Whether a set generated with `recorded` arguments is the one `args` asks for: the
    springtime binary that imports a bake (`--springtime PATH`) is a tool, not a parameter of the
    takes, so another path does not re-bake the set (a re-bake is not bit-identical)."""
    def takes(xs):
        return [x for i, x in enumerate(xs)
                if x != "--springtime" and (i == 0 or xs[i - 1] != "--springtime")]
    return takes(recorded) == takes(args)


def generate(sim, material, a) -> Path:
    out = a.out / "data" / set_name(sim, material, a)
    args = generator_args(sim, material, a)
    record = out / "bench-args.json"
    if (record.exists() and same_takes(json.loads(record.read_text()), args)
            and (out / "test").is_dir()):
        return out
    py = venv_python(a.venvs, sim)
    if out.exists():
        shutil.rmtree(out)
    print(f"[{out.name}] generating: {SIMS[sim]['script'].name} {' '.join(args)}", flush=True)
    t0 = time.time()
    subprocess.run([str(py), str(SIMS[sim]["script"]), str(out), *args], check=True)
    record.write_text(json.dumps(args))
    print(f"[{out.name}] generated in {time.time() - t0:.0f} s", flush=True)
    return out


def capture(sim, material, data: Path, a) -> Path:
    """The capture-grade copy of a set (`capture.py`: noise, missing markers), made once."""
    noise, missing = a.capture
    out = a.out / "data" / f"{data.name}-capture-{noise:g}-{missing:g}"
    args = [str(data), str(out), "--noise", str(noise), "--missing", str(missing),
            "--seed", str(a.seed)]
    record = out / "capture-args.json"
    # The copies' format: 2 writes `position_noise`.
    wanted = {"args": args, "source": (data / "bench-args.json").read_text(), "format": 2}
    same = record.exists() and json.loads(record.read_text()) == wanted
    if not same:
        py = venv_python(a.venvs, sim)
        subprocess.run([str(py), str(HERE / "capture.py"), *args], check=True)
        record.write_text(json.dumps(wanted))
    return out


def spread(sim, material, data: Path, a):
    """The source's own spread (`--spread EPS`): the set's test takes re-run with the material
    perturbed (made once, beside the set), measured against the originals by takes_rmse.py."""
    eps = a.spread
    if not SIMS[sim].get("perturb"):
        return {"spread_error": f"{sim}'s generator takes no --perturb"}
    out = data.parent / f"{data.name}-perturb-{eps:g}"
    args = json.loads((data / "bench-args.json").read_text())
    args += [*SIMS[sim]["perturb"], str(eps)]
    record = out / "bench-args.json"
    py = venv_python(a.venvs, sim)
    if not (record.exists() and json.loads(record.read_text()) == args and (out / "test").is_dir()):
        if out.exists():
            shutil.rmtree(out)
        print(f"[{out.name}] generating: {SIMS[sim]['script'].name} {' '.join(args)}", flush=True)
        done = subprocess.run([str(py), str(SIMS[sim]["script"]), str(out), *args])
        if done.returncode != 0:
            return {"spread_error": f"generation failed (exit {done.returncode})"}
        record.write_text(json.dumps(args))
    found = out / "spread.json"
    done = subprocess.run([str(py), str(HERE / "takes_rmse.py"), str(data / "test"), str(out / "test"),
                           "--json", str(found)], stdout=subprocess.DEVNULL)
    if done.returncode != 0:
        return {"spread_error": f"takes_rmse.py failed (exit {done.returncode})"}
    c = json.loads(found.read_text())
    return {"spread_eps": eps, "spread_short": c["short"], "spread_long": c["long"],
            "spread_half_seconds": c["half_seconds"]}


def train(sim, material, data: Path, a):
    name = set_name(sim, material, a) + ("-capture" if a.capture else "")
    run = a.out / "runs" / a.tag / name
    cmd = [str(a.springtime), "train", str(a.config), "--out", str(run), "--force",
           "--set", f"data.dir={data / 'train'}", "--set", f"data.test_dir={data / 'test'}",
           "--set", "eval.uniform_baseline=true"]
    for s in a.set:
        cmd += ["--set", s]
    print(f"[{name}] {' '.join(cmd)}", flush=True)
    t0 = time.time()
    log = a.out / "runs" / a.tag / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as fh:
        done = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT)
    wall = time.time() - t0
    row = {"data": name, "wall_s": wall, "log": str(log), "run": str(run)}
    if done.returncode != 0:
        tail = log.read_text().strip().splitlines()[-3:]
        row["error"] = " / ".join(tail)
        return row
    ev = json.loads((run / "eval.json").read_text())
    u = ev["uniform_baseline"]
    source = json.loads((data / "source.json").read_text()) if (data / "source.json").exists() else {}
    row.update({
        "short_s": ev["motion_rmse"]["short"]["seconds"],
        "long_s": ev["motion_rmse"]["long"]["seconds"],
        "trained_short": ev["motion_rmse"]["short"]["mean"],
        "trained_long": ev["motion_rmse"]["long"]["mean"],
        "uniform_short": u["test"]["short"]["mean"],
        "uniform_long": u["test"]["long"]["mean"],
        "uniform_k": u["k"],
        "gain_short": u["improvement_short"],
        "gain_long": u["improvement_long"],
        "spearman": ev.get("stiffness_map_corr"),
        # Where the run kept the uniform network (`train.uniform_fallback`): its learned map's.
        "learned_spearman": ev.get("learned_map_corr"),
        "test_takes": len(ev["test_rollouts"]),
        "substeps": substeps_of(run),
        "validation_wins": (ev.get("validation") or {}).get("wins"),
        "source": {k: source.get(k) for k in ("simulator", "version", "material") if k in source},
    })
    # The same network with its bending springs sized apart: what the map's spatial variation
    # wins beyond the bending springs' share.
    row.update(yardstick_figures(u.get("bending_apart"), "bending_apart", "bending_factor", "factor"))
    # The uniform network with its own drag and viscosity: the yardstick above runs at the run's
    # kept physics, chosen for the map.
    row.update(yardstick_figures(u.get("own_damping"), "own_damping", "found_by", "found_by"))
    if a.source_map:
        row.update(source_map(run, a))
    return row


def yardstick_figures(y, name, what, label):
    """A second yardstick's row entries (`uniform_baseline.<name>`): its test RMSE, the trained
    network's gains over it, and `what` it found (as `<name>_<label>`); none where eval.json has
    none."""
    if not y:
        return {}
    return {f"{name}_{label}": y[what],
            f"{name}_short": y["test"]["short"]["mean"], f"{name}_long": y["test"]["long"]["mean"],
            f"gain_{name}_short": y["improvement_short"], f"gain_{name}_long": y["improvement_long"]}


def source_map(run: Path, a):
    """`springtime diagnose RUN`'s source-map reference: the gains of the source's own map, sized."""
    log = run.parent / f"{run.name}-diagnose.log"
    cmd = [str(a.springtime), "diagnose", str(run), "--force"]
    t0 = time.time()
    with open(log, "w") as fh:
        done = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT)
    found = run / "diagnose" / "source_map.json"
    if done.returncode != 0 or not found.exists():
        return {"source_map_error": " / ".join(log.read_text().strip().splitlines()[-2:])}
    c = json.loads(found.read_text())
    return {"source_map_short": c["gain_short"], "source_map_long": c["gain_long"],
            "source_map_k_factor": c["search"]["k_factor"], "source_map_wall_s": time.time() - t0}


def substeps_of(run: Path):
    for line in (run / "config.toml").read_text().splitlines():
        if line.strip().startswith("substeps"):
            return line.split("=", 1)[1].strip()
    return None


def table(rows, a):
    extra = [name for name, on in ((" source's map short / long |", a.source_map),
                                   (f" source ±{100 * (a.spread or 0):g} %: short / whole take (m) |", a.spread))
             if on]
    head = ("| data | trained: short / whole take (m) | best uniform (m) | gain short / long | "
            "over bending-apart short / long | over uniform, own damping | Spearman | substeps | "
            "wall |" + "".join(extra)
            + "\n|---|---|---|---|---|---|---|---|---|" + "---|" * len(extra) + "\n")
    lines = []
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['data']} | failed: {r['error']} | | | | | | | {r['wall_s']:.0f} s |"
                         + " |" * len(extra))
            continue
        sp = "—" if r["spearman"] is None else f"{r['spearman']:.2f}"
        if r.get("learned_spearman") is not None:
            sp += f" (uniform kept; learned {r['learned_spearman']:.2f})"
        lines.append(
            f"| {r['data']} | {r['trained_short']:.3f} / {r['trained_long']:.3f} | "
            f"k {r['uniform_k']:.4g}: {r['uniform_short']:.3f} / {r['uniform_long']:.3f} | "
            f"{100 * r['gain_short']:+.1f} % / {100 * r['gain_long']:+.1f} % | {bending_apart_cell(r)} | "
            f"{own_damping_cell(r)} | {sp} | "
            f"{r['substeps']} | {r['wall_s']:.0f} s |" + (cell(r) if a.source_map else "")
            + (spread_cell(r) if a.spread else ""))
    return head + "\n".join(lines) + "\n"


def bending_apart_cell(r):
    """The gains over the bending-apart network (`uniform_baseline.bending_apart`), with its factor."""
    if "gain_bending_apart_short" not in r:
        return "—"
    return (f"{100 * r['gain_bending_apart_short']:+.1f} % / {100 * r['gain_bending_apart_long']:+.1f} % "
            f"(× {r['bending_apart_factor']:g})")


def own_damping_cell(r):
    """The gains over the uniform network with its own damping (`uniform_baseline.own_damping`),
    with the search that found it."""
    if "gain_own_damping_short" not in r:
        return "—"
    return (f"{100 * r['gain_own_damping_short']:+.1f} % / {100 * r['gain_own_damping_long']:+.1f} % "
            f"({r['own_damping_found_by']})")


def spread_cell(r):
    """The source's own spread's cell of a row."""
    if "spread_short" in r:
        return f" {r['spread_short']:.3f} / {r['spread_long']:.3f} |"
    return f" {r.get('spread_error', '—')} |"


def cell(r):
    """The source-map reference's cell of a row."""
    if "source_map_short" in r:
        return f" {100 * r['source_map_short']:+.1f} % / {100 * r['source_map_long']:+.1f} % |"
    return f" {r.get('source_map_error', '—')} |"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("--sims", default=",".join(SIMS), help="comma-separated, of: " + ", ".join(SIMS))
    ap.add_argument("--materials", default="soft,stiff")
    ap.add_argument("--out", type=Path, default=ROOT / "data" / "foreign")
    ap.add_argument("--venvs", type=Path, default=Path.home() / ".cache" / "springtime-foreign")
    ap.add_argument("--springtime", type=Path, default=ROOT / "target" / "release" / "springtime")
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "thirdparty_mesh.toml")
    ap.add_argument("--set", action="append", default=[], help="passed to `springtime train --set`")
    ap.add_argument("--tag", default="recipe", help="names the runs' folder and the table")
    ap.add_argument("--train", type=int, default=12, help="training takes per set")
    ap.add_argument("--test", type=int, default=12,
                    help="test takes per set (12: four decide little between networks a few points apart; the book's tables before 2026-11-29 used 4, the first four of the same seed stream)")
    ap.add_argument("--seconds", type=float, default=3.0, help="length of a take")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="6 + 2 takes of 2 s (a smoke test)")
    ap.add_argument("--generate-only", action="store_true")
    ap.add_argument("--source-map", action="store_true",
                    help="also run `springtime diagnose` on each run and add its source-map "
                         "reference (the source's own stiffness map, sized) to the table")
    ap.add_argument("--capture", metavar="NOISE,MISSING",
                    help="train and test on capture-grade copies of each set: NOISE m of position "
                         "noise and a MISSING share of markers hidden (capture.py), e.g. 0.002,0.1")
    ap.add_argument("--spread", type=float, metavar="EPS",
                    help="also re-run each set's test takes with every triangle's material times "
                         "1 + EPS * N(0, 1) (Warp and Newton) and add how far they land from the "
                         "originals: the source's own spread, e.g. 0.01")
    ap.add_argument("--variant", metavar="NAME=ARGS",
                    help="another configuration of each simulator: ARGS appended to its "
                         "generator's arguments (a later option wins), the sets named "
                         "<sim>-<material>-NAME, e.g. \"fps30=--fps 30 --res 21 --seed 11\" (the "
                         "generators' options: `python SCRIPT --help`)")
    a = ap.parse_args()
    a.variant_name, a.variant_args = None, []
    if a.variant:
        name, sep, args = a.variant.partition("=")
        if not sep or not name or not name.replace("-", "").isalnum():
            die(f"--variant: expected NAME=ARGS with NAME letters, digits or '-', got {a.variant!r}")
        a.variant_name, a.variant_args = name, shlex.split(args)
    if a.capture:
        try:
            a.capture = tuple(float(v) for v in a.capture.split(","))
            assert len(a.capture) == 2
        except (ValueError, AssertionError):
            die(f"--capture: expected NOISE,MISSING (e.g. 0.002,0.1), got {a.capture!r}")
    if a.spread is not None and not 0.0 < a.spread < 0.3:
        die(f"--spread: expected 0 < EPS < 0.3, got {a.spread}")
    if a.quick:
        a.train, a.test, a.seconds = 6, 2, 2.0
    sims = [s for s in a.sims.split(",") if s]
    for s in sims:
        if s not in SIMS:
            die(f"--sims: unknown simulator {s!r} (known: {', '.join(SIMS)})")
    materials = [m for m in a.materials.split(",") if m]
    for m in materials:
        if m not in ("soft", "stiff"):
            die(f"--materials: unknown material {m!r} (soft, stiff)")
    if not a.generate_only and not a.springtime.exists():
        die(f"no springtime binary at {a.springtime}: run `cargo build --release` or pass --springtime")
    a.springtime = a.springtime.resolve()
    a.out = a.out.resolve()
    rows = []
    for sim in sims:
        for material in materials:
            try:
                data = generate(sim, material, a)
            except subprocess.CalledProcessError as e:
                rows.append({"data": set_name(sim, material, a), "wall_s": 0.0,
                             "error": f"generation failed ({e})"})
                continue
            source = data
            if a.capture:
                data = capture(sim, material, data, a)
            if not a.generate_only:
                rows.append(train(sim, material, data, a))
                if a.spread and "error" not in rows[-1]:
                    # the spread of the source itself: against the takes before any capture noise
                    rows[-1].update(spread(sim, material, source, a))
                print(table(rows[-1:], a), flush=True)
    if a.generate_only:
        return
    text = table(rows, a)
    print(text)
    (a.out / f"bench-{a.tag}.md").write_text(text)
    (a.out / f"bench-{a.tag}.json").write_text(json.dumps(rows, indent=1))
    print(f"table: {a.out / f'bench-{a.tag}.md'}")


if __name__ == "__main__":
    main()
