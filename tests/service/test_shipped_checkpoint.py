"""The shipped HalfCheetah checkpoint, served for real: a mid-episode goal change over REST changes the gait.

A real HalfCheetah-v5 is stepped through a real server on a loopback port: the lowest goal for 400 steps, then
the highest goal through `PUT /sessions/{id}/goal`. Each segment's mean x-velocity (after 100 settle-in steps)
must be within the evaluation tolerance of its goal's dataset mean.
"""

from pathlib import Path

import gymnasium as gym
import httpx
import numpy as np
import pytest
from service_harness import RunningServer, make_settings

from model.checkpoint import load_checkpoint
from model.evaluate import tolerance

SHIPPED = Path(__file__).resolve().parents[2] / "checkpoints" / "halfcheetah-gmt"
SWITCH, STEPS, SETTLE = 400, 800, 100


@pytest.fixture(scope="module")
def shipped_server():
    assert (SHIPPED / "gmt.json").is_file(), f"the shipped default checkpoint {SHIPPED} is missing"
    s = RunningServer(make_settings(checkpoints=[SHIPPED])).start()
    yield s
    s.stop()


def test_switch_lowest_to_highest_mid_episode(shipped_server):
    goals = load_checkpoint(SHIPPED).goals
    low, high = goals[0], goals[-1]
    env = gym.make("HalfCheetah-v5")
    obs, _ = env.reset(seed=0)
    vel = []
    with httpx.Client(base_url=shipped_server.url, timeout=30) as http:
        # A fixed seed: the sampled noise (and so the episode) is then reproducible; `gmt eval` measures the
        # success rate over 15 seeds (switch lowest -> highest: 15/15 at the protocol's step 500).
        r = http.post("/sessions", json={"model": "halfcheetah-gmt", "goal": "lowest", "seed": 0})
        assert r.status_code == 201, r.text
        sid = r.json()["session_id"]
        for t in range(STEPS):
            if t == SWITCH:
                r = http.put(f"/sessions/{sid}/goal", json={"goal": high.id})
                assert r.status_code == 200 and r.json()["goal"] == high.id, r.text
            r = http.post(f"/sessions/{sid}/act", json={"observation": obs.tolist()})
            assert r.status_code == 200, r.text
            body = r.json()
            assert body["step"] == t and body["goal"] == (low.id if t < SWITCH else high.id)
            obs, _, terminated, truncated, info = env.step(np.asarray(body["action"], dtype=np.float32))
            assert not terminated
            vel.append(info["x_velocity"])
        assert http.delete(f"/sessions/{sid}").status_code == 204
    env.close()
    first = float(np.mean(vel[SETTLE:SWITCH]))
    second = float(np.mean(vel[SWITCH + SETTLE :]))
    assert abs(first - low.mean) <= tolerance(low, goals), (first, low.mean)
    assert abs(second - high.mean) <= tolerance(high, goals), (second, high.mean)
