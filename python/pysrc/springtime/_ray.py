"""Run a springtime sweep plan on a Ray cluster: one Ray task per job index (`springtime.sweep`,
and `python -m springtime.sweep`).

    import springtime
    rows = springtime.sweep("plan.toml", "runs/plan", address=None)

or from a shell, on any node of the cluster:

    python -m springtime.sweep plan.toml --out runs/plan [--address HOST:PORT]

Every task calls the same contract as `springtime sweep PLAN --index I --out OUT`, so a job's
figures do not depend on which engine or machine ran it: a finished job is skipped, a job whose
worker was lost is retried by Ray and resumes from its last checkpoint. The results are gathered
as `springtime sweep PLAN --gather` does (`OUT/sweep.csv`, `sweep.md`) and returned as the
table's rows; the figure `sweep.png` and report pages (`report = true`) are the command line's
(`springtime sweep PLAN --gather`, `springtime report DIR`), which the Python package leaves out.

Paths: the plan, the output folder, the base config and the data folders are read from the
driver's working directory; on a cluster of several machines they must be on a filesystem every
node mounts at the same path.
"""

import argparse
import os
import sys
import time

from . import _springtime as _native


def _run_job(plan, index, out, cwd):
    """One Ray task: job `index` of `plan` into `out`, from the driver's working directory."""
    os.chdir(cwd)
    started = time.time()
    result = _native.sweep_index(plan, index, out)
    result["task_seconds"] = time.time() - started
    return result


def _first_line(error):
    text = str(error).strip().splitlines()
    return text[-1] if text else type(error).__name__


def sweep(plan, out=None, address=None, *, cpus_per_task=1, max_retries=3, indices=None,
          verbose=True):
    """Runs every job of `plan` (or those in `indices`) as Ray tasks and gathers the table.

    - `plan`: the plan file (TOML; see `springtime sweep --help`).
    - `out`: output folder (default `runs/<plan name>`).
    - `address`: the Ray cluster (`"HOST:PORT"`, `"auto"`); `None` connects to a cluster
      started on this machine with `ray start`, or starts a local one.
    - `cpus_per_task`: CPUs each job declares; its threads are limited to as many.
    - `max_retries`: how often a job whose worker or node was lost is run again (it resumes).
    - `indices`: a subset of job indices (default all).

    Returns the gathered rows: dicts with `index`, one key per axis, `status`, `rmse_k`,
    `rmse_b`, `motion_rmse_short`, `motion_rmse_long`, … (`OUT/sweep.csv`'s columns). A job
    that fails is listed there with its error; it does not stop the others.
    """
    try:
        import ray
    except ImportError as e:
        raise ImportError(
            "springtime.sweep runs on Ray, which is not installed: "
            "pip install \"./python[ray]\" (or pip install ray)"
        ) from e
    plan = os.path.abspath(os.fspath(plan))
    out = os.path.abspath(os.fspath(out) if out is not None else _native.sweep_default_out(plan))
    jobs = _native.sweep_list(plan)
    if indices is not None:
        wanted = set(int(i) for i in indices)
        unknown = wanted - {j["index"] for j in jobs}
        if unknown:
            raise ValueError(f"indices {sorted(unknown)} are not jobs of {plan} (0 to {len(jobs) - 1})")
        jobs = [j for j in jobs if j["index"] in wanted]
    started_here = not ray.is_initialized()
    if started_here:
        ray.init(address=address, log_to_driver=False)
    task = ray.remote(_run_job).options(
        num_cpus=cpus_per_task,
        max_retries=max_retries,
        retry_exceptions=False,
        runtime_env={"env_vars": {"RAYON_NUM_THREADS": str(max(1, int(cpus_per_task)))}},
    )
    start = time.time()
    cwd = os.getcwd()
    pending = {task.remote(plan, j["index"], out, cwd): j for j in jobs}
    done = 0
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                job = pending.pop(ref)
                done += 1
                try:
                    r = ray.get(ref)
                    if r["status"] == "skipped":
                        what = "already finished"
                    else:
                        what = f"finished in {r['seconds']:.1f} s on {r['host']}"
                        if r.get("resumed"):
                            what += " (resumed)"
                except Exception as e:  # a failed job is recorded; the others go on
                    what = f"failed: {_first_line(e)}"
                if verbose:
                    print(f"[{done}/{len(jobs)}] job {job['index']} ({job['dir']}): {what}; "
                          f"{time.time() - start:.1f} s", file=sys.stderr, flush=True)
    finally:
        for ref in pending:
            ray.cancel(ref)
        if started_here:
            ray.shutdown()
    return _native.sweep_gather(plan, out)


def main(argv=None):
    p = argparse.ArgumentParser(
        prog="python -m springtime.sweep",
        description="Run a springtime sweep plan on a Ray cluster and gather its table.",
    )
    p.add_argument("plan", help="the plan file (TOML)")
    p.add_argument("--out", help="output folder (default runs/<plan name>)")
    p.add_argument("--address", help="Ray cluster address (default: a local cluster)")
    p.add_argument("--cpus-per-task", type=float, default=1, help="CPUs per job (default 1)")
    p.add_argument("--max-retries", type=int, default=3,
                   help="runs of a job whose worker was lost (default 3)")
    p.add_argument("--index", type=int, action="append",
                   help="run only this job (repeatable; default all)")
    args = p.parse_args(argv)
    cpus = int(args.cpus_per_task) if float(args.cpus_per_task).is_integer() else args.cpus_per_task
    rows = sweep(args.plan, args.out, args.address, cpus_per_task=cpus,
                 max_retries=args.max_retries, indices=args.index)
    counts = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    print(", ".join(f"{n} {s}" for s, n in sorted(counts.items())))
    out = os.path.dirname(rows[0]["dir"]) if rows else args.out
    print(f"wrote {os.path.join(out, 'sweep.csv')}")
    return 0 if counts.get("failed", 0) == 0 else 1
