"""Every local device (issue 19 item 3): the batched evaluation splits its sets, K-pair
training its models, over all local devices, and gives the numbers of one device. Two
CPU devices stand in for two GPUs (``--xla_force_host_platform_device_count``): the
placements and the partitioned programs are JAX's, whatever the device kind."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).parent / "support" / "sharded_run.py"


def _run(tmp_path: Path, n_devices: int) -> dict:
    out = tmp_path / f"devices_{n_devices}.npz"
    env = {**os.environ, "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": os.pathsep.join([str(SCRIPT.parent.parent),
                                          os.environ.get("PYTHONPATH", "")]),
           "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "")
                         + f" --xla_force_host_platform_device_count={n_devices}")}
    subprocess.run([sys.executable, str(SCRIPT), str(out)], env=env, check=True,
                   timeout=900)
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def test_evaluation_and_training_spread_over_two_devices_with_the_numbers_of_one(tmp_path):
    one, two = _run(tmp_path, 1), _run(tmp_path, 2)
    assert int(one["devices"]) == 1 and int(two["devices"]) == 2
    # Really spread: the estimates and the trained models live on both devices.
    assert int(two["eval_devices"]) == 2 and int(two["train_devices"]) == 2
    for k in ("x_T", "x_TA"):  # float64 solves: the same arithmetic per set
        np.testing.assert_allclose(two[k], one[k], rtol=1e-9, atol=1e-12, err_msg=k)
    # float32 networks; each model's steps are its own, so the split changes no sum.
    np.testing.assert_allclose(two["history"], one["history"], rtol=1e-5, err_msg="history")
    np.testing.assert_allclose(two["weights"], one["weights"], rtol=1e-4, atol=1e-6,
                               err_msg="trained weights")
