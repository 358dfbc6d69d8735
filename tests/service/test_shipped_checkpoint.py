"""The shipped checkpoints, served for real: the evaluation protocol's switch between the extreme goals.

For every shipped checkpoint of a MuJoCo task, real environments are stepped through a real server on a loopback
port as `gmt eval` judges a switch (docs/architecture.md, "Evaluation protocol"): the lowest goal, then the highest from step 500 through
`PUT /sessions/{id}/goal` (and the reverse), 1000 steps, for two seeds; the four sessions act together through
`POST /act`. Each segment's mean x-velocity after its settle-in must be within the evaluation tolerance of its
goal's dataset mean, and no episode may end early (a fall fails, as in `gmt eval`).
"""

import json
from pathlib import Path

import gymnasium as gym
import httpx
import numpy as np
import pytest
from service_harness import RunningServer, make_settings

from gmt.common.segments import achieved, tolerance, within
from gmt.model.checkpoint import load_checkpoint
from gmt.model.evaluate import protocol

ROOT = Path(__file__).resolve().parents[2] / "checkpoints"
SHIPPED = sorted(
    p.parent for p in ROOT.glob("*/gmt.json") if json.loads(p.read_text())["statistic"] == "mean_x_velocity"
)
# Seeds of the environment resets and the sessions (the sampled noise), as `gmt eval --seeds 2` draws them; each
# checkpoint's eval.json has the success rate over 15.
SEEDS = (0, 1)


def test_the_default_checkpoint_is_shipped():
    assert (ROOT / "halfcheetah-gmt" / "gmt.json").is_file(), "the shipped default checkpoint is missing"


@pytest.fixture(scope="module")
def shipped_server():
    s = RunningServer(make_settings(checkpoints=SHIPPED)).start()
    yield s
    s.stop()


@pytest.mark.parametrize("ckpt_dir", SHIPPED, ids=lambda p: p.name)
def test_the_protocols_switch_between_the_extreme_goals(shipped_server, ckpt_dir):
    ckpt = load_checkpoint(ckpt_dir)
    goals = ckpt.goals
    low, high = goals[0].id, goals[-1].id
    conds = {c.name: c for c in protocol(len(goals))}
    # Both directions, both seeds: four episodes in lockstep, one `POST /act` per step for all of them.
    runs = [(conds[f"switch {a}->{b}"], seed) for a, b in ((low, high), (high, low)) for seed in SEEDS]
    steps = runs[0][0].steps
    assert steps == 1000 and all(
        c.schedule[1][0] == 500 for c, _ in runs
    )  # the evaluation protocol: the switch at step 500
    envs = [gym.make(ckpt.env_id) for _ in runs]
    obs = [env.reset(seed=seed)[0] for env, (_, seed) in zip(envs, runs, strict=True)]
    vel = np.zeros((len(runs), steps))
    with httpx.Client(base_url=shipped_server.url, timeout=30) as http:
        sids = []
        for c, seed in runs:
            r = http.post("/sessions", json={"model": ckpt.name, "goal": c.goal_at(0), "seed": seed})
            assert r.status_code == 201, r.text
            sids.append(r.json()["session_id"])
        for t in range(steps):
            for sid, (c, _) in zip(sids, runs, strict=True):
                if t > 0 and c.goal_at(t) != c.goal_at(t - 1):
                    r = http.put(f"/sessions/{sid}/goal", json={"goal": c.goal_at(t)})
                    assert r.status_code == 200 and r.json()["goal"] == c.goal_at(t), r.text
            items = [
                {"session_id": s, "observation": o.tolist(), "step": t}
                for s, o in zip(sids, obs, strict=True)
            ]
            r = http.post("/act", json={"requests": items})
            assert r.status_code == 200, r.text
            for i, res in enumerate(r.json()["results"]):
                (c, seed), env = runs[i], envs[i]
                assert res["step"] == t and res["goal"] == c.goal_at(t), (c.name, seed, res)
                obs[i], _, terminated, _, info = env.step(np.asarray(res["action"], dtype=np.float32))
                assert not terminated, f"{ckpt.name} {c.name} seed {seed} fell at step {t}"
                vel[i, t] = info["x_velocity"]
        for sid in sids:
            assert http.delete(f"/sessions/{sid}").status_code == 204
    for env in envs:
        env.close()
    for i, (c, seed) in enumerate(runs):
        for goal_id, start, end in c.segments:
            goal = goals[goal_id]
            got = achieved(vel[i], start, end)
            assert within(got, goal.mean, tolerance(goal, goals)), (
                c.name,
                seed,
                goal.name,
                (start, end),
                got,
                goal.mean,
            )
