"""The issue's goals counted over bench runs: which sets meet them and how many of each kind.

    python3 benches/foreign/goals.py data/foreign/runs/s28a data/foreign/runs/s28b ...
    python3 benches/foreign/goals.py 'data/foreign/runs/s28*' --markdown

Each argument is a run folder of `springtime train` (with `eval.json`) or a folder of them, as
`benches/foreign/run.py --tag T` writes to `data/foreign/runs/T/` (a quoted glob is expanded
here). A set's name is its run folder's: `<sim>-<material>` is one of the bench's ten sets,
`<sim>-<material>-capture…` a capture-grade copy (`run.py --capture`), any other suffix another
configuration (`run.py --variant`). Where a set was run more than once, the last argument that
holds it wins, so later tags override earlier ones.

The goals (all on the held-out test takes, `eval.json`): the trained surrogate beats the best
uniform network (`uniform_baseline.test`) by at least 20 % at the short horizon (0.8 s) and over
the whole take, and the learned structural `k` ranks with the source's stiffness map at Spearman
(`stiffness_map_corr`) 0.7 or more; on the capture copies 10 % and 0.6. A run that kept a
uniform network has no rank (`—`); the map it set aside (`learned_map_corr`) is shown beside, in
parentheses, and does not count. Where the set's takes were also re-run with the source's
material perturbed (`run.py --spread EPS`: `<set>-perturb-EPS/spread.json` beside the set's
data; the smallest EPS is shown), the column "source ±EPS" gives how far the source misses its
own takes over the whole take, and the gain over the best uniform network a surrogate that
close would have: where that is near 20 %, the goal asks for the source's own precision.
Where `eval.json` holds each test take's figure (`per_rollout`, springtime from 2026-12-06),
the column "90 % interval" gives a paired bootstrap interval of each gain over the draw of the
test takes (the takes resampled with replacement, the trained and the uniform network's
figures of a take kept together; 5,000 draws, a fixed seed): how far the set's gain could
move with another twelve takes from the same generator. Needs only the standard library.
"""
import argparse
import glob
import json
import random
import re
import sys
from pathlib import Path

SIMS = ("blender", "warp", "newton", "mujoco", "tpcloth")
MATERIALS = ("soft", "stiff")
GOALS = {"bench": (0.20, 0.70), "other configurations": (0.20, 0.70), "capture copies": (0.10, 0.60)}


def kind(name):
    """The set's kind: one of the bench's ten sets, a capture copy or another configuration."""
    if re.fullmatch(rf"({'|'.join(SIMS)})-({'|'.join(MATERIALS)})", name):
        return "bench"
    if re.search(r"-capture(-|$)", name):
        return "capture copies"
    return "other configurations"


def run_folders(arguments):
    """Every run folder the arguments name, in order (a folder of runs: its runs, sorted)."""
    for argument in arguments:
        paths = sorted(glob.glob(argument)) or [argument]
        for path in map(Path, paths):
            if (path / "eval.json").is_file():
                yield path
            elif path.is_dir():
                yield from sorted(p.parent for p in path.glob("*/eval.json"))
            else:
                sys.exit(f"{path}: neither a run folder (eval.json) nor a folder of runs")


def row(run):
    """The goal's figures of one run, or exits naming the file and key it lacks."""
    source = run / "eval.json"
    try:
        e = json.loads(source.read_text())
        trained, uniform = e["motion_rmse"], e["uniform_baseline"]["test"]
        figures = {
            "trained": (trained["short"]["mean"], trained["long"]["mean"]),
            "uniform": (uniform["short"]["mean"], uniform["long"]["mean"]),
        }
    except (OSError, ValueError) as err:
        sys.exit(f"{source}: {err}")
    except (KeyError, TypeError) as err:
        sys.exit(f"{source}: no {err} (an eval with `eval.uniform_baseline = true` writes it)")
    gains = tuple(1.0 - t / u for t, u in zip(figures["trained"], figures["uniform"]))
    intervals = tuple(interval(trained[h].get("per_rollout"), uniform[h].get("per_rollout"))
                      for h in ("short", "long"))
    compression = None
    blend = run / "blend.json"
    if blend.is_file():
        found = json.loads(blend.read_text()).get("shear_compression")
        if found:
            kept = found["kept"]
            compression = (found["shear_compression"] if kept else 1.0,
                           found.get("shear_share", 1.0) if kept else 1.0)
    return {
        "spread": spread(e, source),
        "set": run.name,
        "run": str(run),
        "gains": gains,
        "intervals": None if None in intervals else intervals,
        "spearman": e.get("stiffness_map_corr"),
        "set_aside": e.get("learned_map_corr"),
        "compression": compression,
        **figures,
    }


def shear(found):
    """The shear springs as the run keeps them: their stiffness in compression per unit k (κ) and,
    where the search changed it, their share of their k (σ); blank without the search."""
    if found is None:
        return ""
    kappa, share = found
    return f"{kappa:g}" + ("" if share == 1.0 else f" · {share:.2f}")


def interval(trained, uniform, draws=5000, level=0.90):
    """The paired bootstrap interval of the gain `1 − Σ trained / Σ uniform` over the takes, or
    None where either network's per-take figures are missing or do not pair up."""
    if not trained or not uniform or len(trained) != len(uniform):
        return None
    rng = random.Random(0)
    n = len(trained)
    gains = []
    for _ in range(draws):
        picks = [rng.randrange(n) for _ in range(n)]
        gains.append(1.0 - sum(trained[i] for i in picks) / sum(uniform[i] for i in picks))
    gains.sort()
    tail = (1.0 - level) / 2
    return gains[int(tail * draws)], gains[int((1.0 - tail) * draws) - 1]


def spread(e, source):
    """(eps, whole-take RMSE) of the source's own spread on the run's test takes, the smallest
    eps found beside the set's data, or None."""
    tests = e.get("test_rollouts") or []
    if not tests:
        return None
    data = Path(tests[0]).parent.parent  # <data>/<set>/test/take.npz
    found = []
    for path in data.parent.glob(f"{glob.escape(data.name)}-perturb-*/spread.json"):
        try:
            eps = float(path.parent.name.rsplit("-perturb-", 1)[1])
            found.append((eps, float(json.loads(path.read_text())["long"])))
        except (ValueError, KeyError, TypeError) as err:
            sys.exit(f"{path} (the spread of {source}'s takes): {err!r}")
    return min(found) if found else None


def met(r):
    gain, rank = GOALS[kind(r["set"])]
    return min(r["gains"]) >= gain and (r["spearman"] or -1.0) >= rank


def misses(r):
    """What the set misses, in words."""
    gain, rank = GOALS[kind(r["set"])]
    out = [h for h, g in zip(("0.8 s", "the take"), r["gains"]) if g < gain]
    if r["spearman"] is None:
        out.append("rank (a uniform network kept)")
    elif r["spearman"] < rank:
        out.append("rank")
    return ", ".join(out)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run folders, folders of runs, or quoted globs")
    p.add_argument("--markdown", action="store_true", help="a Markdown table")
    a = p.parse_args()
    latest = {}
    for run in run_folders(a.runs):
        r = row(run)
        latest.pop(r["set"], None)
        latest[r["set"]] = r
    if not latest:
        sys.exit("no runs with eval.json among the arguments")
    rows = sorted(latest.values(), key=lambda r: (list(GOALS).index(kind(r["set"])), r["set"]))
    rank = lambda v: "—" if v is None else f"{v:.2f}"
    spreads = any(r["spread"] for r in rows)
    intervals = any(r["intervals"] for r in rows)
    if a.markdown:
        print("| set | trained, m | best uniform, m | gain 0.8 s / take | Spearman | κ · σ |"
              + (" source ±EPS: take, m (its gain) |" if spreads else "")
              + (" 90 % interval: 0.8 s / take |" if intervals else "") + " goals |")
        print("|---|---|---|---|---|---|" + ("---|" if spreads else "") + ("---|" if intervals else "")
              + "---|")
    for r in rows:
        spearman = rank(r["spearman"]) + (f" ({rank(r['set_aside'])})" if r["set_aside"] is not None else "")
        cells = [
            r["set"],
            "{:.4f} / {:.4f}".format(*r["trained"]),
            "{:.4f} / {:.4f}".format(*r["uniform"]),
            "{:+.1f} % / {:+.1f} %".format(*(100 * g for g in r["gains"])),
            spearman,
            shear(r["compression"]),
        ]
        widths = [28, 17, 17, 19, 12, 9]
        if spreads:
            cells.append("" if r["spread"] is None else "±{:g} %: {:.4f} ({:+.1f} %)".format(
                100 * r["spread"][0], r["spread"][1], 100 * (1.0 - r["spread"][1] / r["uniform"][1])))
            widths.append(26)
        if intervals:
            cells.append("" if r["intervals"] is None else " / ".join(
                "{:+.0f} … {:+.0f} %".format(100 * lo, 100 * hi) for lo, hi in r["intervals"]))
            widths.append(25)
        cells.append("✓" if met(r) else "misses " + misses(r))
        widths.append(0)
        if a.markdown:
            print("| " + " | ".join(cells) + " |")
        else:
            print("  ".join(f"{c:<{w}}" for c, w in zip(cells, widths)).rstrip())
    print()
    for k in GOALS:
        of_kind = [r for r in rows if kind(r["set"]) == k]
        if of_kind:
            gain, rank_goal = GOALS[k]
            print(f"{k}: {sum(map(met, of_kind))} of {len(of_kind)} meet the goals "
                  f"(≥ {100 * gain:.0f} % at both horizons, Spearman ≥ {rank_goal})")


if __name__ == "__main__":
    main()
