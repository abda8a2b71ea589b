"""The Python example runs as documented and reproduces the main job's figures."""

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_python_quickstart_example_trains_evaluates_and_simulates(tmp_path):
    # Run from a scratch folder holding the shipped config, as from a checkout's root.
    (tmp_path / "configs").mkdir()
    shutil.copy(ROOT / "configs" / "quickstart.toml", tmp_path / "configs")
    out = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "python" / "quickstart.py")],
        cwd=tmp_path, capture_output=True, text=True, check=True,
    ).stdout
    # The README's quickstart figure (rmse_k 2.2243 N/m) and a swing that stays finite.
    assert "rmse_k 2.2242" in out, out
    assert "simulated (2001, 100, 3)" in out, out
    assert (tmp_path / "runs" / "example-python" / "eval.json").is_file()
