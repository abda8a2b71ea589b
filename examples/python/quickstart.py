"""The Python quickstart: train the quickstart cloth, evaluate it, simulate it from NumPy.

    pip install ./python          # once, from the repository root
    python examples/python/quickstart.py

The same steps as `springtime train configs/quickstart.toml`, through the bindings; the run
goes to `runs/example-python/`.
"""

import numpy as np

import springtime

# Train (generating the data first when `data.dir` holds none) and evaluate on the test takes.
run = springtime.train("configs/quickstart.toml", set=['name="example-python"'], force=True)
report = run.evaluate()
print(run)
print("rmse_k", report["rmse_k"], "N/m; motion RMSE (long horizon)",
      report["motion_rmse"]["long"]["mean"], "m")

# Simulate two seconds from rest with the learned springs: positions as NumPy arrays.
# The first row of particles is pinned where it rests; the rest of the sheet swings under gravity.
x0 = run.rest
pinned = np.abs(x0[:, 1] - x0[:, 1].max()) < 1e-9
positions, velocities = run.simulate(x0, int(round(2.0 / run.frame_dt)), pinned=pinned.tolist())
print("simulated", positions.shape, "lowest point after 2 s:", float(positions[-1, :, 2].min()), "m")
