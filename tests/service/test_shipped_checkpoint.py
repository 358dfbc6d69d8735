"""The shipped checkpoints, served for real: a mid-episode goal change over REST changes the gait.

For every shipped checkpoint of a MuJoCo task, a real environment is stepped through a real server on a loopback
port: the lowest goal for 400 steps, then the highest goal through `PUT /sessions/{id}/goal` (and the reverse).
Each segment's mean x-velocity (after 100 settle-in steps) must be within the evaluation tolerance of its goal's
dataset mean, and the episode must not end early (a fall fails, as in `gmt eval`).
"""

import json
from pathlib import Path

import gymnasium as gym
import httpx
import numpy as np
import pytest
from service_harness import RunningServer, make_settings

from gmt.model.checkpoint import load_checkpoint
from gmt.model.evaluate import tolerance

ROOT = Path(__file__).resolve().parents[2] / "checkpoints"
SHIPPED = sorted(
    p.parent for p in ROOT.glob("*/gmt.json") if json.loads(p.read_text())["statistic"] == "mean_x_velocity"
)
SWITCH, STEPS, SETTLE = 400, 800, 100


def test_the_default_checkpoint_is_shipped():
    assert (ROOT / "halfcheetah-gmt" / "gmt.json").is_file(), "the shipped default checkpoint is missing"


@pytest.fixture(scope="module")
def shipped_server():
    s = RunningServer(make_settings(checkpoints=SHIPPED)).start()
    yield s
    s.stop()


@pytest.mark.parametrize("direction", ["up", "down"])
@pytest.mark.parametrize("ckpt_dir", SHIPPED, ids=lambda p: p.name)
def test_switch_between_the_extreme_goals_mid_episode(shipped_server, ckpt_dir, direction):
    ckpt = load_checkpoint(ckpt_dir)
    goals = ckpt.goals
    first, then = (goals[0], goals[-1]) if direction == "up" else (goals[-1], goals[0])
    env = gym.make(ckpt.env_id)
    obs, _ = env.reset(seed=0)
    vel = []
    with httpx.Client(base_url=shipped_server.url, timeout=30) as http:
        # A fixed seed: the sampled noise (and so the episode) is then reproducible; `gmt eval` measures the
        # success rate over 15 seeds (each checkpoint's eval.json).
        r = http.post("/sessions", json={"model": ckpt.name, "goal": first.id, "seed": 0})
        assert r.status_code == 201, r.text
        sid = r.json()["session_id"]
        for t in range(STEPS):
            if t == SWITCH:
                r = http.put(f"/sessions/{sid}/goal", json={"goal": then.id})
                assert r.status_code == 200 and r.json()["goal"] == then.id, r.text
            r = http.post(f"/sessions/{sid}/act", json={"observation": obs.tolist()})
            assert r.status_code == 200, r.text
            body = r.json()
            assert body["step"] == t and body["goal"] == (first.id if t < SWITCH else then.id)
            obs, _, terminated, truncated, info = env.step(np.asarray(body["action"], dtype=np.float32))
            assert not terminated, f"{ckpt.name} fell at step {t}"
            vel.append(info["x_velocity"])
        assert http.delete(f"/sessions/{sid}").status_code == 204
    env.close()
    before = float(np.mean(vel[SETTLE:SWITCH]))
    after = float(np.mean(vel[SWITCH + SETTLE :]))
    assert abs(before - first.mean) <= tolerance(first, goals), (before, first.mean)
    assert abs(after - then.mean) <= tolerance(then, goals), (after, then.mean)
