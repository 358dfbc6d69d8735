"""Data-parallel training: two torchrun processes on CPU follow one process with the same global batch."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from safetensors.numpy import load_file

from gmt.model.data.minari_io import Episode, write_dataset
from gmt.model.fixtures import SyntheticDataset

BIN = Path(sys.executable).parent


def _write(tmp_path: Path) -> Path:
    """SyntheticDataset on disk, its goal as the episodes' x-velocity (so relabelling finds its 3 goals)."""
    ds = SyntheticDataset(n_episodes=12, length=30)
    episodes = [
        Episode(
            observations=ep.observations,
            actions=ep.actions,
            rewards=np.zeros(len(ep.actions), np.float32),
            terminated=False,
            truncated=True,
            infos={"x_velocity": np.full(len(ep.actions), g + 0.01 * i)},
            final_observation=None,
            episode_id=i,
        )
        for i, (ep, g) in enumerate(zip(ds.episodes, ds.labels, strict=True))
    ]
    write_dataset("t/synthetic/ddp-v0", episodes, ds.env_id, ds.observation_space, ds.action_space, tmp_path)
    return tmp_path / "t/synthetic/ddp-v0"


@pytest.mark.skipif(not (BIN / "torchrun").exists(), reason="torchrun is installed with torch")
def test_two_processes_follow_one_process_with_the_same_global_batch(tmp_path):
    dataset = _write(tmp_path)
    args = [
        "train",
        "--dataset",
        str(dataset),
        "--k",
        "3",
        "--steps",
        "8",
        "--batch-size",
        "8",
        "--lr",
        "3e-3",
    ]
    args += [
        "--warmup-steps",
        "1",
        "--context-length",
        "4",
        "--n-layer",
        "1",
        "--n-embd",
        "16",
        "--threads",
        "1",
    ]
    args += ["--calibration-batches", "1", "--log-every", "1", "--device", "cpu", "--masking", "token"]
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1"}
    env.pop("WORLD_SIZE", None)
    one, two = tmp_path / "one", tmp_path / "two"
    res = subprocess.run(
        [str(BIN / "gmt"), *args, "--out", str(one)], env=env, capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr[-3000:]
    torchrun = [str(BIN / "torchrun"), "--standalone", "--nproc-per-node", "2", str(BIN / "gmt")]
    res = subprocess.run([*torchrun, *args, "--out", str(two)], env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr[-3000:]
    a, b = (json.loads((d / "gmt.json").read_text())["training"] for d in (one, two))
    assert (a["processes"], b["processes"]) == (1, 2)
    curve_a, curve_b = np.array(a["loss_curve"]), np.array(b["loss_curve"])
    assert len(curve_a) == 8 and curve_a[-1, 1] < curve_a[0, 1]  # it trains
    np.testing.assert_allclose(curve_b, curve_a, rtol=1e-4)
    wa, wb = (load_file(str(d / "model.safetensors")) for d in (one, two))
    assert wa.keys() == wb.keys()
    for k in wa:
        np.testing.assert_allclose(wb[k], wa[k], atol=1e-5, err_msg=k)
