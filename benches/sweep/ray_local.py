"""A sweep on a local Ray cluster started like a real one, against the same jobs run serially.

    python benches/sweep/ray_local.py [--bin target/release/springtime] [--jobs 8] [--kill]

Needs the Python package with Ray (`pip install "./python[ray]"`) and the `springtime` binary.
It:
1. writes a plan of N quickstart jobs (seeds × initial stiffness) and generates their data once;
2. runs every index serially through `deploy/slurm/sweep.sbatch` (a Slurm array simulated by a
   loop setting SLURM_ARRAY_TASK_ID), then `--gather`; and once more with one thread per job;
3. starts a Ray head (`ray start --head`, no CPUs of its own) on 127.0.0.1 and a worker process
   joining it with two CPUs, and runs the plan there with `python -m springtime.sweep`;
4. with `--kill`, runs it again into a fresh folder and SIGKILLs the Ray worker process of a job
   mid-training (after its first checkpoint): Ray retries the task and the job resumes;
5. prints the wall times, the per-task overhead, and whether every figure equals the serial
   run's (learned k and b, motion RMSE at both horizons, the gathered table).
"""

import argparse
import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def run(cmd, **kw):
    return subprocess.run(cmd, check=True, **kw)


def figures(job):
    springs = np.load(job / "springs.npz")
    ev = json.loads((job / "eval.json").read_text())
    return (springs["k"].tobytes(), springs["b"].tobytes(),
            ev["motion_rmse"]["short"]["mean"], ev["motion_rmse"]["long"]["mean"])


def table(out):
    with open(out / "sweep.csv") as f:
        return [{k: v for k, v in r.items() if k not in ("seconds", "dir")}
                for r in csv.DictReader(f)]


def job_seconds(out):
    return sum(json.loads(p.read_text())["seconds"] for p in out.glob("*/sweep_job.json"))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bin", default=str(ROOT / "target" / "release" / "springtime"))
    p.add_argument("--jobs", type=int, default=8, help="jobs in the plan (even; default 8)")
    p.add_argument("--kill", action="store_true", help="also the run with a worker killed")
    p.add_argument("--port", type=int, default=6390)
    p.add_argument("--keep", action="store_true", help="keep the scratch folder")
    args = p.parse_args()
    binary = os.path.abspath(args.bin)
    work = Path(tempfile.mkdtemp(prefix="springtime-ray-"))
    seeds = list(range(args.jobs // 2))
    plan = work / "plan.toml"
    plan.write_text(
        f'base = "{ROOT / "configs" / "quickstart.toml"}"\n'
        f'set = ["data.dir={work / "data"}"]\n'
        f'[axes]\n"train.seed" = {seeds}\n"model.k_init" = [40.0, 60.0]\n')
    print(f"plan: {args.jobs} quickstart jobs in {work}", flush=True)
    run([binary, "generate", str(ROOT / "configs" / "quickstart.toml"),
         "--set", f"data.dir={work / 'data'}"], cwd=work, stdout=subprocess.DEVNULL)

    # A Slurm array simulated by a loop: deploy/slurm/sweep.sbatch once per array index.
    slurm = dict(os.environ, PLAN=str(plan), OUT=str(work / "serial"),
                 PATH=os.path.dirname(binary) + os.pathsep + os.environ["PATH"])
    slurm.pop("SLURM_CPUS_PER_TASK", None)
    slurm.pop("RAYON_NUM_THREADS", None)
    start = time.time()
    for i in range(args.jobs):
        run(["bash", str(ROOT / "deploy" / "slurm" / "sweep.sbatch")], cwd=work,
            env=dict(slurm, SLURM_ARRAY_TASK_ID=str(i), SLURM_CPUS_PER_TASK="2"),
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    serial = time.time() - start
    run([binary, "sweep", str(plan), "--gather", "--out", str(work / "serial")], cwd=work,
        stdout=subprocess.DEVNULL)
    print(f"serial (deploy/slurm/sweep.sbatch per index, 2 threads per job): {serial:.1f} s",
          flush=True)
    # The same with one thread per job, as each Ray task gets: what the scheduling alone buys.
    start = time.time()
    for i in range(args.jobs):
        run([binary, "sweep", str(plan), "--index", str(i), "--out", str(work / "serial1")],
            cwd=work, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env=dict(os.environ, RAYON_NUM_THREADS="1"))
    serial1 = time.time() - start
    same1 = all(figures(j) == figures(work / "serial" / j.name)
                for j in (work / "serial1").iterdir() if j.is_dir())
    print(f"serial, one thread per job: {serial1:.1f} s; every figure equal to the default "
          f"threads': {same1}", flush=True)

    ray = shutil.which("ray", path=os.path.dirname(sys.executable)) or "ray"
    # Token authentication as on a real cluster: head, worker and driver share ~/.ray/auth_token.
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0", RAY_AUTH_MODE="token")
    if not (Path.home() / ".ray" / "auth_token").exists():
        run([ray, "get-auth-token", "--generate"], env=env, stdout=subprocess.DEVNULL)
    address = f"127.0.0.1:{args.port}"
    head = [ray, "start", "--head", "--node-ip-address=127.0.0.1", f"--port={args.port}",
            "--num-cpus=0", "--include-dashboard=false", "--disable-usage-stats"]
    worker = [ray, "start", f"--address={address}", "--node-ip-address=127.0.0.1",
              "--num-cpus=2", "--disable-usage-stats"]
    run(head, env=env, stdout=subprocess.DEVNULL)
    try:
        run(worker, env=env, stdout=subprocess.DEVNULL)
        results = {}
        for name, kill in [("ray", False)] + ([("ray-killed", True)] if args.kill else []):
            out = work / name
            cmd = [sys.executable, "-m", "springtime.sweep", str(plan), "--out", str(out),
                   "--address", address]
            start = time.time()
            proc = subprocess.Popen(cmd, cwd=work, env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True)
            killed = None
            if kill:
                killed = kill_a_job_mid_training(out)
            log = proc.communicate()[0]
            wall = time.time() - start
            if proc.returncode != 0:
                print(log)
                raise SystemExit(f"{name}: python -m springtime.sweep failed")
            same = all(figures(out / j.name) == figures(work / "serial" / j.name)
                       for j in (work / "serial").iterdir() if j.is_dir())
            resumed = [json.loads(r.read_text())["index"] for r in out.glob("*/sweep_job.json")
                       if json.loads(r.read_text())["resumed"]]
            overhead = (wall * 2 - job_seconds(out)) / args.jobs
            results[name] = wall
            print(f"{name}: {wall:.1f} s wall ({wall / serial:.2f} × serial, {wall / serial1:.2f} × "
                  f"serial with one thread per job); per-task overhead "
                  f"{overhead:.2f} s ((wall × 2 CPUs − Σ job seconds) / jobs); every figure equal "
                  f"to serial: {same}; table equal: {table(out) == table(work / 'serial')}"
                  + (f"; killed worker pid {killed}, resumed jobs {resumed}" if kill else ""),
                  flush=True)
    finally:
        run([ray, "stop", "--force"], env=env, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL)
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


def kill_a_job_mid_training(out):
    """SIGKILLs the Ray worker process training a job once that job has a checkpoint on disk."""
    deadline = time.time() + 120
    while time.time() < deadline:
        for state in out.glob("*/run.json"):
            try:
                s = json.loads(state.read_text())
            except (OSError, ValueError):
                continue
            if s.get("status") == "running" and s.get("checkpoint", 0) > 0:
                pids = subprocess.run(["pgrep", "-f", "ray::_run_job"], capture_output=True,
                                      text=True).stdout.split()
                if pids:
                    os.kill(int(pids[0]), signal.SIGKILL)
                    return int(pids[0])
        time.sleep(0.01)
    raise SystemExit("no job reached a checkpoint within 120 s")


if __name__ == "__main__":
    main()
