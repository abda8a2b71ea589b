"""Learning from another simulator's data, end to end (the book, "Data from another simulator").

`tests/thirdparty/tpcloth.py` is an independent NumPy cloth simulator (neo-Hookean membrane,
RK4, area-lumped masses, edge dashpots and air drag, an irregular jittered mesh, pinned anchors,
100 fps frames without velocities, extra metadata keys). On its rollouts the shipped recipe
`configs/thirdparty_mesh.toml` (the surrogate on the data's own mesh) must learn the stiffness
map and beat the best uniform network, and do better than the paper's grid over the same
landmarks. Measured with the recipe of the cross-simulator round (least squares and the
strain-compliance map, blended into the best uniform network; 2 cores): data mesh Spearman 0.64,
+27.6 % over the best uniform network at 3 s and +35.6 % at 0.8 s; 13 x 13 grid Spearman 0.35,
+7.5 % and +30.4 %, test RMSE 0.315 m against the mesh's 0.249 m (with the least-squares start
and scale search before it: mesh 0.63, +23.7 %, +29.8 %; grid -0.19, -54 %, -97 %).

How far the mesh beats the uniform network depends on the takes' rounding: the same command,
NumPy and recipe (1f55314) gave +19.1 % / +12.6 % (0.8 s / 3 s, Spearman 0.73) on one machine
and +6.1 % / +3.4 % (Spearman 0.79; the grid -4.1 % / -4.7 %, Spearman 0.29, 0.2966 m against
the mesh's 0.2958 m over the take) on another (2026-12-04; on the second, 12 test takes instead
of 3 give +4.0 % / +3.4 %: the training takes decide it, not the test takes' few). On the
second machine the recipe of 2026-12-05 (the mixed map weighed by its halves, kept alone; the
polish's rows picked with their neighbours) gains +14.7 % / +5.4 %, Spearman 0.79, 0.2705 m over
the take against the grid's 0.2913 m (grid Spearman 0.17). So the test
asserts what the recipe promises on every machine: the learned map ranks the source's (> 0.4),
the surrogate is not worse than the best uniform network at either horizon, and the data's own
mesh beats the paper's grid; the bench (`benches/foreign/run.py`) measures by how much.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

import springtime

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "configs" / "thirdparty_mesh.toml"
TPCLOTH = ROOT / "tests" / "thirdparty" / "tpcloth.py"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """12 training and 3 test rollouts of 3 s of a 2 m jittered 13 x 13 sheet with stripes
    and a patch of Young's modulus 66 / 266 / 666 N/m (about a minute of NumPy)."""
    out = tmp_path_factory.mktemp("tpcloth") / "tp"
    subprocess.run(
        [sys.executable, str(TPCLOTH), str(out), "--rollouts", "12", "--test", "3",
         "--seconds", "3", "--res", "13", "--size", "2", "--young", "66", "266", "666",
         "--fps", "100", "--pin-radius", "0.15", "--seed", "21"],
        check=True,
        capture_output=True,
    )
    return out


def train(data, out, extra=()):
    run = springtime.train(
        str(RECIPE),
        out=str(out),
        set=[f"data.dir={data / 'train'}", f"data.test_dir={data / 'test'}", *extra],
    )
    ev = json.loads((Path(run.path) / "eval.json").read_text())
    ev["blend"] = json.loads((Path(run.path) / "blend.json").read_text())
    return ev


def test_the_data_mesh_learns_another_simulators_map_better_than_a_grid(data, tmp_path):
    mesh = train(data, tmp_path / "mesh")
    gain = mesh["uniform_baseline"]
    assert mesh["stiffness_map_corr"] > 0.4, mesh["stiffness_map_corr"]
    assert gain["improvement_long"] > 0.0, gain
    assert gain["improvement_short"] > 0.0, gain
    # The recipe keeps the mixed map (`train.compliance.keep = "mixed"`), the fit's and the
    # compliance map's shapes weighed by how alike each reads off the two halves of the
    # training takes (`train.compliance.weights = "halves"`): one map searched, its weights
    # recorded per strain group, each between 0 and 1.
    maps = [m["map"] for m in mesh["blend"]["maps"]]
    assert maps == ["mixed"], maps
    assert mesh["blend"]["map"] == "mixed", mesh["blend"]["map"]
    groups = mesh["blend"]["weights"]["groups"]
    assert groups and all(0.0 <= g["fit_weight"] <= 1.0 for g in groups), groups
    # The kept map's figure is its polished blend's.
    assert mesh["blend"]["maps"][0]["after"] == mesh["blend"]["polish"]["after"], mesh["blend"]

    grid = train(
        data, tmp_path / "grid", ["cloth.layout=grid", "cloth.nx=13", "cloth.ny=13"]
    )
    # A grid's particles are interpolated between the data's vertices: it ranks the map less
    # well and moves further from the data than the data's own mesh.
    assert grid["stiffness_map_corr"] < mesh["stiffness_map_corr"], (grid, mesh)
    assert grid["motion_rmse"]["long"]["mean"] > mesh["motion_rmse"]["long"]["mean"]
