"""The Python bindings, as a user meets them after `pip install ./python`.

`cargo test` runs this file through tests/python.rs (a virtual environment with the package
installed); by hand: `pip install ./python pytest && pytest tests/python`.
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
QUICKSTART = ROOT / "configs" / "quickstart.toml"
# The quickstart job made small: a few short rollouts and a few Adam steps per pass.
SMALL = [
    "source.train_rollouts=6",
    "source.test_rollouts=2",
    "source.seconds=0.6",
    "data.clips.steps=50",
    "train.stiffness.iterations=6",
    "train.damping.iterations=3",
    "train.stiffness.batch=4",
    "train.damping.batch=4",
]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished spring run trained through `springtime.train`, with its data folder."""
    work = tmp_path_factory.mktemp("springtime")
    data = work / "data"
    run = springtime.train(
        str(QUICKSTART), out=str(work / "run"), set=SMALL + [f"data.dir={data}"]
    )
    return run, data


def test_train_returns_an_opened_finished_run(trained):
    run, _ = trained
    assert run.kind == "springs"
    assert run.particles == 100
    status = json.loads((Path(run.path) / "run.json").read_text())
    assert status["status"] == "finished"
    assert "springtime.Run(" in repr(run)


def test_load_run_reads_the_trained_springs(trained):
    run, _ = trained
    again = springtime.load_run(run.path)
    stored = np.load(Path(run.path) / "springs.npz")
    assert again.springs.shape == (stored["k"].shape[0], 2)
    np.testing.assert_array_equal(again.springs, stored["springs"])
    np.testing.assert_allclose(again.k, stored["k"], rtol=1e-6)
    np.testing.assert_allclose(again.b, stored["b"], rtol=1e-6)
    assert again.rest.shape == (100, 3) and again.rest.dtype == np.float32
    np.testing.assert_allclose(again.rest[:, 2], 0.0)
    # A grid surrogate's particles weigh the same: the mean.
    assert len(again.masses) == 100
    np.testing.assert_allclose(again.masses, again.particle_mass)
    np.testing.assert_allclose(float(stored["particle_mass"]), again.particle_mass)


def test_a_free_sheet_falls_as_its_centre_of_mass_must(trained):
    """Internal spring forces cancel (Newton's third law), so the mean velocity of a free sheet
    follows v <- v + dt (g - c/m v) exactly, step by step, whatever the springs."""
    run, _ = trained
    phys = run.physics
    x0 = run.rest.copy()
    x0[:, 2] += 1.0
    # Stretched along x, so the springs act while it falls.
    x0[:, 0] *= 1.05
    frames = 40
    positions, velocities = run.simulate(x0, frames)
    assert positions.shape == velocities.shape == (frames + 1, 100, 3)
    assert positions.dtype == np.float32
    np.testing.assert_array_equal(positions[0], x0)
    g = np.array(phys["gravity"])
    h, damp = phys["dt"], phys["rayleigh"] / phys["mass"]
    assert phys["viscosity"] == 0.0  # sim.viscosity: none in this run
    v = np.zeros(3)
    x = x0.astype(np.float64).mean(axis=0)
    for _ in range(frames * phys["substeps"]):
        v = v + h * (g - damp * v)
        x = x + h * v
    np.testing.assert_allclose(velocities[-1].mean(axis=0), v, atol=2e-4 * np.abs(v).max())
    np.testing.assert_allclose(positions[-1].mean(axis=0), x, atol=1e-4)
    # ... while the stretched sheet itself contracts: the springs did act.
    span = positions[:, :, 0].max(axis=1) - positions[:, :, 0].min(axis=1)
    assert span[-1] < span[0]


def test_pinned_particles_follow_their_path(trained):
    run, _ = trained
    x0 = run.rest.copy()
    pinned = [False] * run.particles
    pinned[0] = pinned[9] = True
    frames = 20
    path = np.repeat(x0[None], frames + 1, axis=0)
    lift = np.linspace(0.0, 0.3, frames + 1, dtype=np.float32)
    path[:, 0, 2] += lift
    path[:, 9, 2] += lift
    positions, _ = run.simulate(x0, frames, pinned=pinned, path=path)
    np.testing.assert_allclose(positions[:, [0, 9]], path[:, [0, 9]], atol=1e-5)
    # The free particles hang below the pins.
    assert positions[-1, 50, 2] < positions[-1, 0, 2] - 0.01


def test_simulate_file_equals_the_command_line(trained, tmp_path):
    run, data = trained
    rollout = sorted(data.glob("test_*.npz"))[0]
    binary = os.environ.get("SPRINGTIME_BIN") or shutil.which("springtime")
    if binary is None:
        pytest.skip("no springtime binary: set SPRINGTIME_BIN")
    out = tmp_path / "cli.npz"
    subprocess.run(
        [binary, "simulate", run.path, "--init", str(rollout), "--seconds", "0.3",
         "--out", str(out)],
        check=True,
        capture_output=True,
    )
    cli = np.load(out)["positions"]
    positions, velocities = run.simulate_file(str(rollout), frames=cli.shape[0] - 1)
    assert positions.shape == cli.shape
    np.testing.assert_allclose(positions, cli, rtol=0, atol=1e-6)
    assert np.isfinite(velocities).all()


def test_evaluate_returns_what_it_writes(trained):
    run, _ = trained
    report = run.evaluate()
    written = json.loads((Path(run.path) / "eval.json").read_text())
    assert report["motion_rmse"]["mean"] == pytest.approx(written["motion_rmse"]["mean"])
    assert np.isfinite(report["motion_rmse"]["mean"]) and report["motion_rmse"]["mean"] > 0
    assert report["rmse_k"] is not None


def test_bad_input_names_what_is_wrong(trained, tmp_path):
    run, _ = trained
    with pytest.raises(ValueError, match="x0"):
        run.simulate(np.zeros((7, 3)), 3)
    with pytest.raises(ValueError, match="path"):
        run.simulate(run.rest, 3, pinned=[True] * run.particles, path=np.zeros((2, 5, 3)))
    with pytest.raises(ValueError, match="pinned"):
        run.simulate(run.rest, 3, pinned=[True, False])
    missing = tmp_path / "no_such_run"
    with pytest.raises(RuntimeError, match="no_such_run"):
        springtime.load_run(str(missing))
    with pytest.raises(RuntimeError, match="not_there.toml"):
        springtime.train(str(tmp_path / "not_there.toml"))


def test_version():
    assert springtime.__version__
    assert springtime.__version__ in springtime.version()
