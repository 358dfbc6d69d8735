import json

import numpy as np
import pytest

pytest.importorskip("ale_py")
pytest.importorskip("cv2")

from gmt.datagen import breakout as b  # noqa: E402
from gmt.model.data.minari_io import load_dataset  # noqa: E402
from gmt.model.data.statistics import get_statistic, per_trajectory  # noqa: E402


@pytest.fixture(scope="module")
def env():
    e = b.make_env()
    yield e
    e.close()


def test_ram_gives_ball_paddle_and_score(env):
    env.reset(seed=0)
    assert not b.read_ram(env).in_play  # no ball until FIRE
    _, _, _, _, _ = env.step(b.FIRE)
    env.step(b.NOOP)
    s = b.read_ram(env)
    assert s.in_play and 0 < s.ball_y < b.PADDLE_Y
    assert b.WALL_LEFT <= s.ball_x <= b.WALL_RIGHT and b.PADDLE_MIN <= s.paddle_x <= b.PADDLE_MAX
    # Left alone, the ball falls past the paddle (y grows beyond PADDLE_Y), then is gone and a life is lost.
    ys, lives = [], None
    for _ in range(40):
        _, _, _, _, info = env.step(b.NOOP)
        ys.append(b.read_ram(env).ball_y)
        lives = info["lives"]
    falling = ys[: ys.index(0)]
    assert np.all(np.diff(falling) > 0) and falling[-1] > b.PADDLE_Y and lives == 4
    moved = [b.read_ram(env).paddle_x]
    for action in (b.RIGHT, b.RIGHT, b.LEFT, b.LEFT, b.LEFT, b.NOOP):
        env.step(action)
        moved.append(b.read_ram(env).paddle_x)
    assert moved[2] > moved[0] and moved[-1] < moved[2]  # RIGHT moves the paddle right, LEFT back
    # With the paddle kept under it (the calibrated offset), it bounces back up instead.
    env.reset(seed=0)
    agent, rng, ys = b.TrackingAgent(b.Skill("aim")), np.random.default_rng(0), []  # predicts the landing x
    for _ in range(60):
        env.step(agent.act(b.read_ram(env), rng))
        ys.append(b.read_ram(env).ball_y)
    top = int(np.argmax(ys))
    assert b.PADDLE_Y - 10 <= ys[top] <= b.PADDLE_Y and ys[top + 1] < ys[top]


def test_tracking_agent_beats_random(env):
    cap = 400
    rng = np.random.default_rng(0)
    strong = b.play(env, b.make_agent("strong"), 7, rng, cap)
    random = b.play(env, b.make_agent("random"), 7, rng, cap)
    assert strong.ret >= random.ret + 5
    assert strong.lives[-1] > random.lives[-1]
    # The RAM score is the sum of the rewards.
    assert b.read_ram(env).score == random.ret
    assert strong.observations.dtype == np.uint8 and strong.observations.shape == (cap + 1, 4, 64, 64)


def test_reflect_folds_between_walls():
    assert b._reflect(100.0) == 100.0
    assert b._reflect(b.WALL_RIGHT + 10.0) == b.WALL_RIGHT - 10.0
    assert b._reflect(b.WALL_LEFT - 10.0) == b.WALL_LEFT + 10.0


def test_bursts_split_at_paddle_touches_and_lost_balls():
    # Ball falls to the paddle (y 160 -> 180), turns up, breaks a brick (4 points), comes back, turns up again,
    # then scores 7 + 7 + 7 behind the wall before being lost (y 0).
    ball_y = [0, 100, 140, 160, 180, 150, 100, 150, 175, 140, 90, 60, 70, 60, 200, 0]
    rewards = [0, 0, 0, 0, 0, 4, 0, 0, 0, 0, 7, 7, 7, 0, 0]
    np.testing.assert_array_equal(b.bursts(np.array(ball_y), np.array(rewards)), [0, 4, 21, 0])
    assert b.bursts(np.array([0]), np.array([])).tolist() == [0]


def test_tiny_collection_reads_back(tmp_path):
    cfg = b.CollectConfig(
        episodes={"random": 1, "strong": 2},
        max_steps=40,
        seed=1,
        data_dir=tmp_path,
        dataset_id="gmt/bt/tiny-v0",
    )
    res = b.collect_breakout(cfg, progress=False)
    assert res.episodes == 3 and res.transitions == 120
    ds = load_dataset("gmt/bt/tiny-v0", tmp_path)
    assert ds.env_id == "ALE/Breakout-v5" and ds.action_space.n == 4
    assert ds.observation_space.shape == (4, 64, 64) and ds.observation_space.dtype == np.uint8
    for ep in ds.episodes:
        assert ep.observations.dtype == np.uint8 and ep.observations.shape == (40, 4, 64, 64)
        assert ep.truncated and not ep.terminated
        assert ep.actions.dtype == np.int64 and set(ep.actions) <= {0, 1, 2, 3}
        assert ep.infos["lives"].shape == (40,)
        # Frame stacking: each observation's first three frames are the previous one's last three.
        np.testing.assert_array_equal(ep.observations[1:, :3], ep.observations[:-1, 1:])
    returns = per_trajectory("return", ds)
    np.testing.assert_allclose(returns, [float(ep.rewards.sum()) for ep in ds.episodes])
    # The statistic over a segment is the sum of that segment's rewards.
    ep = ds.episodes[1]
    assert get_statistic("return").aggregate(ep.rewards[10:30]) == pytest.approx(
        float(ep.rewards[10:30].sum())
    )
    meta = json.loads((res.path / "metadata.json").read_text())
    assert meta["preprocessing"]["observation_shape"] == [4, 64, 64] and meta["max_episode_steps"] == 40
    assert ds.preprocessing == meta["preprocessing"]  # what a checkpoint trained on it declares
    assert meta["jpeg_encoding"] is False and meta["max_burst"] == 30
    import h5py

    with h5py.File(res.path / "main_data.hdf5") as f:
        assert f["episode_0"]["observations"].compression == "gzip"
        assert f["episode_1"].attrs["policy"] == "strong"
        assert f["episode_1"].attrs["return"] == returns[1]
        assert 0 <= f["episode_1"].attrs["max_burst"] <= returns[1]
    again = b.collect_breakout(
        b.CollectConfig(
            episodes={"random": 1, "strong": 2}, max_steps=40, seed=1, data_dir=tmp_path,
            dataset_id="gmt/bt/again-v0", compress=0,
        ),
        progress=False,
    )  # fmt: skip
    assert load_dataset(again.dataset_id, tmp_path).fingerprint == ds.fingerprint  # seeded, lossless
    assert again.bytes > res.bytes


def test_episodes_with_a_burst_are_replaced(tmp_path):
    cfg = b.CollectConfig(
        episodes={"strong": 1}, max_steps=100, data_dir=tmp_path, dataset_id="gmt/bt/b-v0", max_burst=0,
        max_attempts=2,
    )  # fmt: skip
    with pytest.raises(RuntimeError, match="2 of 2 episodes had a burst of more than 0 points"):
        b.collect_breakout(cfg, progress=False)


def test_config_and_cli_reject_bad_input():
    with pytest.raises(ValueError, match="unknown level"):
        b.CollectConfig(episodes={"expert": 3})
    with pytest.raises(ValueError, match="must be >= 1"):
        b.CollectConfig(episodes={"random": 0})
    with pytest.raises(ValueError, match="max_steps"):
        b.CollectConfig(max_steps=0)
    assert b._parse_episodes(["random=3", "strong=2"]) == {"random": 3, "strong": 2}


def test_main_collects_and_measures(tmp_path, capsys):
    argv = ["--episodes", "random=1", "weak=1", "--max-steps", "10", "--data-dir", str(tmp_path)]
    assert b.main([*argv, "--out-id", "gmt/bt/cli-v0", "--no-progress"]) == 0
    assert len(load_dataset("gmt/bt/cli-v0", tmp_path).episodes) == 2
    assert b.main([*argv, "--measure", "1"]) == 0
    out = capsys.readouterr().out
    assert "2 episodes, 20 transitions" in out and '"mean_length": 10.0' in out


def test_gmt_data_collect_dispatches_breakout_to_the_scripted_agents(tmp_path):
    from typer.testing import CliRunner

    from gmt.model.data.minari_io import load_dataset
    from gmt.service.cli import app

    args = ["data", "collect", "--env", "ALE/Breakout-v5", "--episodes-per-level", "1", "--max-steps", "12"]
    r = CliRunner().invoke(app, [*args, "--data-dir", str(tmp_path), "--out-id", "t/breakout/cli-v0"])
    assert r.exit_code == 0, r.output
    ds = load_dataset("t/breakout/cli-v0", tmp_path)
    assert len(ds.episodes) == 5 and all(len(ep) <= 12 for ep in ds.episodes)
    assert ds.episodes[0].observations.dtype == np.uint8


def test_a_late_reaction_waits_for_the_ball_by_a_rule_of_what_is_visible():
    """A `react_y` level keeps still while the descending ball is above its line, then moves; no randomness."""
    rng = np.random.default_rng(0)
    late, prompt = b.TrackingAgent(b.LEVELS["late152"]), b.TrackingAgent(b.Skill("prompt"))
    far = 60  # the paddle sits far left of a ball coming down on the right
    high = [b.RamState(170, 100, far, 0), b.RamState(172, 106, far, 0)]  # descending, above 152
    low = [b.RamState(170, 150, far, 0), b.RamState(172, 156, far, 0)]  # descending, below 152
    for agent in (late, prompt):
        agent.reset()
    assert [late.act(s, rng) for s in high][-1] == b.NOOP
    assert [prompt.act(s, rng) for s in high][-1] == b.RIGHT
    late.reset()
    assert [late.act(s, rng) for s in low][-1] == b.RIGHT
    # Deterministic: the same states give the same actions again.
    late.reset()
    again = [late.act(s, rng) for s in high + low]
    late.reset()
    assert [late.act(s, rng) for s in high + low] == again
    assert "reacts below y 152" in b.describe_level("late152") and "random" in b.describe_level("ace")


def test_a_leading_level_aims_a_few_steps_ahead_and_never_past_the_paddle_line():
    """`lead` extrapolates the descending ball by at most `lead` steps (folded at the walls), and by exactly the
    steps left where the ball is closer to the paddle's line than that: then it aims at the landing point."""
    lead, track, land = (b.TrackingAgent(b.LEVELS[n]) for n in ("lead4", "strong", "ace"))
    off = b.PADDLE_OFFSET
    before, now = b.RamState(100, 100, 80, 0), b.RamState(103, 105, 80, 0)  # vx 3, vy 5, 15.6 steps to go
    assert lead.target(now, before) == 103 + 4 * 3 - off
    assert track.target(now, before) == 103 - off
    assert land.target(now, before) == pytest.approx(103 + 3 * (b.PADDLE_Y - 105) / 5 - off)
    near_b, near = b.RamState(100, 170, 80, 0), b.RamState(103, 175, 80, 0)  # 1.6 steps to the paddle line
    assert lead.target(near, near_b) == pytest.approx(land.target(near, near_b))
    wall_b, wall = b.RamState(b.WALL_RIGHT - 7, 100, 80, 0), b.RamState(b.WALL_RIGHT - 4, 105, 80, 0)
    assert lead.target(wall, wall_b) == b.WALL_RIGHT - 8 - off  # 4 + 12 folded back at the right wall
    rising = b.RamState(103, 95, 80, 0)  # ascending: follows the ball's x
    assert lead.target(rising, before) == 103 - off
    assert "tracks the ball 4 steps ahead, reacts below y 152" == b.describe_level("lead152")


def test_the_react_recipe_writes_its_own_dataset_with_its_levels(tmp_path, capsys):
    argv = ["--recipe", "react", "--max-steps", "8", "--data-dir", str(tmp_path), "--no-progress"]
    assert b.main([*argv, "--episodes", "ace=1", "late172=1"]) == 0
    import h5py

    from gmt.model.data.minari_io import resolve

    ds = load_dataset(b.RECIPES["react"].dataset_id, tmp_path)
    assert len(ds.episodes) == 2
    path = resolve(b.RECIPES["react"].dataset_id, tmp_path)
    meta = json.loads((path / "metadata.json").read_text())
    assert (
        meta["max_burst"] == 60.0
        and "late172 (tracks the landing point, reacts below y 172" in meta["description"]
    )
    with h5py.File(path / "main_data.hdf5") as f:
        assert [f[f"episode_{i}"].attrs["policy"] for i in range(2)] == ["ace", "late172"]
    assert set(b.RECIPES["react"].episodes) <= set(b.LEVELS)


def test_a_disturbed_level_records_its_own_action_where_the_game_got_a_random_one(env):
    skill = b.Skill("d", disturb=0.3)
    played = b.play(env, b.TrackingAgent(skill), 11, np.random.default_rng(3), 300)
    differ = played.executed != played.actions
    # a random action equals the level's own one time in four: about 0.3 x 3/4 of the steps differ
    assert 0.12 < differ.mean() < 0.33, differ.mean()
    # the recorded actions are the undisturbed policy's: replaying the executed actions through a fresh agent
    # of the same level (which sees the same states) gives back every recorded action
    env.reset(seed=11)
    clean, rng = b.TrackingAgent(b.Skill("d")), np.random.default_rng(0)
    for executed, recorded in zip(played.executed, played.actions, strict=True):
        assert clean.decide(b.read_ram(env), rng) == recorded
        clean.played(int(executed))
        env.step(int(executed))
    assert "executed_action" in played.to_episode(0).infos
    plain = b.play(env, b.make_agent("strong"), 11, np.random.default_rng(3), 50, keep_frames=False)
    assert plain.executed is None  # levels without disturbances write the same data as before
