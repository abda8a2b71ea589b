"""`springtime.sweep` on a local Ray cluster against the same jobs run serially by the binary.

Skipped with a note where `ray` is not installed; `cargo test` (tests/python.rs) installs it, so CI
runs it.
"""

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import springtime

ROOT = Path(__file__).resolve().parents[2]
# Four small quickstart jobs: two seeds by two initial stiffnesses.
PLAN = """base = "{base}"
set = [
  "source.train_rollouts=6", "source.test_rollouts=2", "source.seconds=0.6",
  "data.clips.steps=50", "train.stiffness.iterations=8", "train.damping.iterations=4",
  "train.stiffness.batch=4", "train.damping.batch=4", "data.dir={data}",
]
[axes]
"train.seed" = [0, 1]
"model.k_init" = [40.0, 60.0]
"""


def figures(job):
    job = Path(job)
    springs = np.load(job / "springs.npz")
    ev = json.loads((job / "eval.json").read_text())
    return (
        springs["k"].tolist(),
        springs["b"].tolist(),
        ev["motion_rmse"]["short"]["mean"],
        ev["motion_rmse"]["long"]["mean"],
    )


def test_a_plan_on_ray_gives_the_serial_figures(tmp_path):
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install './python[ray]')")
    binary = os.environ.get("SPRINGTIME_BIN") or shutil.which("springtime")
    if binary is None:
        pytest.skip("no springtime binary: set SPRINGTIME_BIN")
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN.format(base=ROOT / "configs" / "quickstart.toml", data=tmp_path / "data"))
    jobs = springtime.sweep_list(str(plan))
    assert [j["index"] for j in jobs] == [0, 1, 2, 3]
    assert jobs[1]["overrides"][-2:] == ["train.seed=0", "model.k_init=60.0"]

    # Serially, one process per index, as a Slurm array would.
    for j in jobs:
        subprocess.run([binary, "sweep", str(plan), "--index", str(j["index"]),
                        "--out", str(tmp_path / "serial")], check=True, cwd=tmp_path)

    # On a local Ray cluster: two CPUs, one per job.
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        rows = springtime.sweep(str(plan), str(tmp_path / "ray"), verbose=False)
        # Once more: every job is finished, so every job is skipped and the table is the same.
        again = springtime.sweep(str(plan), str(tmp_path / "ray"), verbose=False)
    finally:
        ray.shutdown()
    assert [r["status"] for r in rows] == ["finished"] * 4
    assert [r["index"] for r in rows] == [0, 1, 2, 3]
    assert [(r["train.seed"], r["model.k_init"]) for r in rows] == [
        (0, 40.0), (0, 60.0), (1, 40.0), (1, 60.0)]
    for r, j in zip(rows, jobs):
        ray_job = tmp_path / "ray" / j["dir"]
        serial_job = tmp_path / "serial" / j["dir"]
        assert figures(ray_job) == figures(serial_job), j["dir"]
        assert r["motion_rmse_long"] == figures(ray_job)[3]
        record = json.loads((ray_job / "sweep_job.json").read_text())
        assert record["status"] == "finished" and not record["resumed"]
    drop = ("seconds", "dir")
    assert [{k: v for k, v in r.items() if k not in drop} for r in again] == [
        {k: v for k, v in r.items() if k not in drop} for r in rows]
    assert (tmp_path / "ray" / "sweep.csv").is_file()
    # The two engines' tables agree too.
    serial_rows = springtime.sweep_gather(str(plan), str(tmp_path / "serial"))
    assert [r["rmse_k"] for r in serial_rows] == [r["rmse_k"] for r in rows]
