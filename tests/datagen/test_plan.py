"""Receding-horizon selection over a commanded level's continuations (`gmt.datagen.plan`), and planned collection."""

import json
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest

from gmt.datagen.collect import CollectConfig, collect
from gmt.datagen.fixtures import random_behaviour
from gmt.datagen.plan import PlanConfig, PlannedPolicy, parse_plan
from gmt.datagen.rollout import rollout
from gmt.model.data.minari_io import load_dataset

ENV = "Hopper-v5"


class ConstantTorque:
    """A 'commanded' policy whose every joint torque is its command: what it does in Hopper is easy to compute."""

    def __init__(self, command: float, mean_speed: float | None = 0.5):
        self.command, self.governor = command, None
        self.meta = SimpleNamespace(mean_speed=mean_speed)
        self.episodes = 0

    def start_episode(self) -> None:
        self.episodes += 1

    def act(self, obs, rng=None):
        return np.full(3, self.command, dtype=np.float32)


def _continuation(command: float, steps: int, seed: int = 0) -> tuple[list[np.ndarray], float, int, bool]:
    """Actions, mean x-velocity, length and fall of `steps` constant-torque steps from the reset pose."""
    env = gym.make(ENV)
    env.reset(seed=seed)
    speeds = []
    for _ in range(steps):
        _, _, terminated, _, info = env.unwrapped.step(np.full(3, command, dtype=np.float32))
        speeds.append(info["x_velocity"])
        if terminated:
            break
    return (
        [np.full(3, command, dtype=np.float32)] * len(speeds),
        float(np.mean(speeds)),
        len(speeds),
        terminated,
    )


@pytest.mark.parametrize("target", [-0.05, 0.45, 0.9])
def test_the_continuation_closest_to_the_target_is_played_and_the_state_restored(target):
    commands = (0.0, 0.3, 1.0)  # all three stand for the 10 simulated steps, at different speeds
    runs = {c: _continuation(c, 10) for c in commands}
    assert not any(fell for *_, fell in runs.values())
    expected = min(commands, key=lambda c: abs(runs[c][1] - target))
    env = gym.make(ENV)
    obs, _ = env.reset(seed=0)
    before = env.unwrapped.data.qpos.copy(), env.unwrapped.data.qvel.copy()
    own = ConstantTorque(0.3)
    planned = PlannedPolicy(
        own, env, PlanConfig(commands, candidates=3, every=4, horizon=10, steps=8, target=target)
    )
    planned.start_episode()
    first = planned.act(obs)
    np.testing.assert_array_equal(
        env.unwrapped.data.qpos, before[0]
    )  # planning left the real state as it was
    np.testing.assert_array_equal(env.unwrapped.data.qvel, before[1])
    assert own.command == 0.3  # and the level's own command
    np.testing.assert_array_equal(first, np.full(3, expected, dtype=np.float32))


def test_survivors_rank_before_falls_and_longer_falls_before_shorter_ones():
    # Torque 0.5 falls after ~26 steps at ~0.7 m/s, 0 stands still for the whole horizon, 1.0 falls sooner.
    assert _continuation(0.0, 80)[3] is False and _continuation(0.5, 80)[3] and _continuation(1.0, 80)[3]
    assert _continuation(0.5, 80)[2] > _continuation(1.0, 80)[2]
    env = gym.make(ENV)
    for commands, expected in [((0.5, 0.0), 0.0), ((1.0, 0.5), 0.5)]:
        obs, _ = env.reset(seed=0)
        cfg = PlanConfig(commands, candidates=2, every=5, horizon=80, steps=5, target=0.7)
        planned = PlannedPolicy(ConstantTorque(0.0), env, cfg)
        planned.start_episode()
        assert planned.act(obs)[0] == expected


def test_only_the_first_steps_are_planned_then_the_level_plays_itself():
    env = gym.make(ENV)
    own = ConstantTorque(0.0, mean_speed=5.0)  # its target: the snapshot's measured speed
    cfg = PlanConfig((0.2,), candidates=1, every=3, horizon=5, steps=7)
    planned = PlannedPolicy(own, env, cfg)
    assert planned.target == 5.0
    ep = rollout(env, planned, seed=0, rng=None, max_steps=12)
    assert own.episodes == 1  # rollout started the episode, and the planner passed it on
    np.testing.assert_array_equal(ep.actions[:7], np.full((7, 3), 0.2, dtype=np.float32))
    np.testing.assert_array_equal(ep.actions[7:], np.zeros((5, 3), dtype=np.float32))
    again = rollout(env, planned, seed=0, rng=None, max_steps=12)  # a new episode plans again from its start
    np.testing.assert_array_equal(again.actions, ep.actions)


def test_plans_and_levels_that_cannot_plan_are_refused():
    assert parse_plan("slow=1.6,1.2") == ("slow", (1.6, 1.2))
    for bad in ["slow", "slow=", "=1.0", "slow=fast", "slow=1.0,x"]:
        with pytest.raises(ValueError, match="LEVEL=COMMAND"):
            parse_plan(bad)
    with pytest.raises(ValueError, match="commands"):
        PlanConfig((float("nan"),))
    with pytest.raises(ValueError, match="every"):
        PlanConfig((1.0,), every=50, horizon=20)
    with pytest.raises(ValueError, match="candidates"):
        PlanConfig((1.0,), candidates=0)
    env = gym.make(ENV)
    with pytest.raises(ValueError, match="commanded"):
        PlannedPolicy(SimpleNamespace(command=None, governor=None), env, PlanConfig((1.0,)))
    with pytest.raises(ValueError, match="target"):
        PlannedPolicy(ConstantTorque(0.0, mean_speed=None), env, PlanConfig((1.0,)))
    with pytest.raises(ValueError, match="without pool starts"):
        CollectConfig(ENV, pool_start={"slow": 0.0}, plan={"slow": PlanConfig((1.0,))})
    # From rest a level needs no pool starts to be planned.
    CollectConfig(ENV, pool_start={"slow": 0.0}, plan={"slow": PlanConfig((1.0,), from_rest=True)})
    with pytest.raises(ValueError, match="need from_rest"):
        PlanConfig((1.0,), rest_target=1.2)
    with pytest.raises(ValueError, match="need from_rest"):
        PlanConfig((1.0,), rest_commands=(3.0,))
    with pytest.raises(ValueError, match="rest_commands must be finite"):
        PlanConfig((1.0,), from_rest=True, rest_commands=(float("nan"),))
    sprint = PlanConfig((1.0, 0.5), from_rest=True, rest_commands=(3.0, 1.0))
    assert sprint.for_rest().commands == (3.0, 1.0) and sprint.commands == (1.0, 0.5)
    with pytest.raises(ValueError, match="rest_target must be finite"):
        PlanConfig((1.0,), from_rest=True, rest_target=float("inf"))
    plan = PlanConfig((1.0,), from_rest=True, rest_target=1.2, target=0.9)
    assert plan.for_rest().target == 1.2 and plan.target == 0.9
    assert PlanConfig((1.0,), from_rest=True, target=0.9).for_rest().target == 0.9


def _commanded_snapshot(folder, level: str, command: float, seed: int) -> None:
    """A random-weight HalfCheetah actor that reads a command appended to its observation."""
    random_behaviour(folder, level, command, seed, weight_scale=0.3, command=command)


def _metadata(root, dataset_id: str) -> list[dict]:
    import h5py

    with h5py.File(root / dataset_id / "data" / "main_data.hdf5", "r") as f:
        return [dict(f[f"episode_{i}"].attrs) for i in range(len(f))]


def _description(root, dataset_id: str) -> str:
    return json.loads((root / dataset_id / "data" / "metadata.json").read_text())["description"]


def test_a_planned_collection_plans_only_that_levels_pool_starts_and_is_reproducible(tmp_path):
    beh, root = tmp_path / "behaviour", tmp_path / "d"
    _commanded_snapshot(beh, "slow", 1.0, 0)
    _commanded_snapshot(beh, "fast", 3.0, 1)
    plan = PlanConfig((1.0, -2.0), candidates=4, every=5, horizon=10, steps=10)

    def run(out_id: str, plans: dict):
        cfg = CollectConfig(
            "HalfCheetah-v5", 4, 3, out_id, root, beh, 30, include_random=False, drop_stuck=False,
            pool_start={"slow": 0.5}, plan=plans,
        )  # fmt: skip
        return collect(cfg, progress=False), load_dataset(out_id, root)

    res, planned = run("gmt/planned-v0", {"slow": plan})
    assert res.levels["slow"]["planned"] == 2 and res.levels["fast"]["planned"] == 0
    meta = _metadata(root, "gmt/planned-v0")
    assert [m["policy"] for m in meta] == ["slow"] * 4 + ["fast"] * 4
    assert [m.get("planned_steps") for m in meta] == [10, 10] + [None] * 6  # pool-started slow episodes only
    _, plain = run("gmt/plain-v0", {})
    for i in range(4, 8):  # the other level's episodes are untouched by the planning
        np.testing.assert_array_equal(planned.episodes[i].actions, plain.episodes[i].actions)
    for i in range(2):  # the same pool starts, but the planned ones chose other actions
        np.testing.assert_array_equal(planned.episodes[i].observations[0], plain.episodes[i].observations[0])
        assert not np.allclose(planned.episodes[i].actions[:10], plain.episodes[i].actions[:10])
    _, again = run("gmt/again-v0", {"slow": plan})
    assert again.fingerprint == planned.fingerprint
    with pytest.raises(ValueError, match=r"unknown levels \['medium'\]"):
        collect(
            CollectConfig("HalfCheetah-v5", 2, 3, data_dir=root, behaviour_dir=beh, include_random=False,
                          pool_start={"slow": 0.5, "medium": 0.5}, plan={"medium": plan}),
            progress=False,
        )  # fmt: skip


def test_a_plan_from_rest_also_plans_the_levels_episodes_that_start_at_the_reset_pose(tmp_path):
    beh, root = tmp_path / "behaviour", tmp_path / "d"
    _commanded_snapshot(beh, "slow", 1.0, 0)
    _commanded_snapshot(beh, "fast", 3.0, 1)
    base = dict(candidates=4, every=5, horizon=10, steps=10)

    def run(out_id: str, plans: dict, pool_start: dict):
        cfg = CollectConfig(
            "HalfCheetah-v5", 4, 3, out_id, root, beh, 30, include_random=False, drop_stuck=False,
            pool_start=pool_start, plan=plans,
        )  # fmt: skip
        return collect(cfg, progress=False), load_dataset(out_id, root)

    pooled = {"slow": 0.5}
    res, rest = run("gmt/rest-v0", {"slow": PlanConfig((1.0, -2.0), from_rest=True, **base)}, pooled)
    assert res.levels["slow"]["planned"] == 4 and res.levels["fast"]["planned"] == 0
    meta = _metadata(root, "gmt/rest-v0")
    assert [m.get("planned_steps") for m in meta] == [10] * 4 + [None] * 4
    # Two pool starts, then two episodes from rest.
    assert ["start_from" in m for m in meta[:4]] == [True, True, False, False]
    _, pool_only = run("gmt/pool-only-v0", {"slow": PlanConfig((1.0, -2.0), **base)}, pooled)
    for i in range(2):  # the pool-started episodes are planned alike either way
        np.testing.assert_array_equal(rest.episodes[i].actions, pool_only.episodes[i].actions)
    for i in range(2, 4):  # the same reset poses, but now planned
        np.testing.assert_array_equal(rest.episodes[i].observations[0], pool_only.episodes[i].observations[0])
        assert not np.allclose(rest.episodes[i].actions[:10], pool_only.episodes[i].actions[:10])
    # A target of its own for the episodes from rest changes only those.
    rt = PlanConfig((1.0, -2.0), from_rest=True, rest_target=-3.0, **base)
    _, urgent = run("gmt/rest-target-v0", {"slow": rt}, pooled)
    for i in range(2):
        np.testing.assert_array_equal(urgent.episodes[i].actions, rest.episodes[i].actions)
    for i in range(2, 4):
        assert not np.allclose(urgent.episodes[i].actions[:10], rest.episodes[i].actions[:10])
    # So do commands of their own for the episodes from rest (a sprint from standing).
    rc = PlanConfig((1.0, -2.0), from_rest=True, rest_commands=(3.0,), **base)
    _, sprint = run("gmt/rest-commands-v0", {"slow": rc}, pooled)
    for i in range(2):
        np.testing.assert_array_equal(sprint.episodes[i].actions, rest.episodes[i].actions)
    for i in range(2, 4):
        assert not np.allclose(sprint.episodes[i].actions[:10], rest.episodes[i].actions[:10])
    assert "from rest with commands 3" in _description(root, "gmt/rest-commands-v0")
    # Without pool starts at all, every episode of the level is planned from rest.
    res, _ = run("gmt/rest-only-v0", {"slow": PlanConfig((1.0, -2.0), from_rest=True, **base)}, {})
    assert res.levels["slow"]["planned"] == 4 and res.levels["slow"]["pool_starts"] == 0
