"""`research.settle`: pool-started episodes that reach their goal too slowly are dropped, the rest kept as they were."""

import gymnasium as gym
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from gmt.model.data.minari_io import Episode, load_dataset, write_dataset
from research.settle import SettleConfig, main, settle_filter

STEPS = 240


def _episode(i: int, speed: np.ndarray, obs_dim: int, act_dim: int, rng) -> Episode:
    return Episode(
        observations=rng.normal(size=(STEPS, obs_dim)),
        actions=rng.uniform(-1, 1, size=(STEPS, act_dim)).astype(np.float32),
        rewards=rng.normal(size=STEPS).astype(np.float32),
        terminated=False,
        truncated=True,
        infos={"x_velocity": speed},
        final_observation=rng.normal(size=obs_dim),
        episode_id=i,
    )


def _speed(start: float, level: float, brake_steps: int, rng) -> np.ndarray:
    """`start` m/s for `brake_steps` steps, then `level`, with a little noise."""
    v = np.full(STEPS, level)
    v[:brake_steps] = start
    return v + rng.normal(0, 0.01, STEPS)


@pytest.fixture
def source(tmp_path):
    """Slow (1 m/s) and fast (2 m/s) episodes; pool-started slow ones brake after 10 or 100 steps."""
    env = gym.make("Hopper-v5")
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    rng = np.random.default_rng(0)
    plan = (
        [("slow", None, 1.0, 0)] * 12  # rest-started slow
        + [("fast", None, 2.0, 0)] * 6  # rest-started fast
        + [("slow", "fast", 1.0, 10)] * 3  # brakes at once: inside 1 +- 0.1 over [50, 200)
        + [("slow", "fast", 1.0, 100)] * 3  # brakes late: mean over [50, 200) ~1.33
        + [("fast", "slow", 2.0, 5)] * 2  # speeds up at once
    )
    episodes, meta = [], []
    for i, (level, start_from, target, brake) in enumerate(plan):
        other = 2.0 if level == "slow" else 1.0
        episodes.append(_episode(i, _speed(other, target, brake, rng), obs_dim, act_dim, rng))
        meta.append({"policy": level, "reset_seed": i, **({"start_from": start_from} if start_from else {})})
    write_dataset(
        "t/hopper/src-v0",
        episodes,
        "Hopper-v5",
        env.observation_space,
        env.action_space,
        tmp_path,
        episode_metadata=meta,
    )
    return tmp_path, episodes, plan


def test_only_the_pool_started_episodes_outside_their_band_are_dropped(source):
    root, episodes, plan = source
    res = settle_filter(SettleConfig("t/hopper/src-v0", "t/hopper/settled-v0", data_dir=root, k=2))
    late = [i for i, p in enumerate(plan) if p[3] == 100]
    expected = [i for i in range(len(plan)) if i not in late]
    assert (res.kept, res.total) == (len(expected), len(plan))
    out = load_dataset("t/hopper/settled-v0", root)
    assert len(out.episodes) == len(expected)
    for ep, i in zip(out.episodes, expected, strict=True):  # the kept ones, unchanged, in order
        np.testing.assert_array_equal(ep.observations, episodes[i].observations)
        np.testing.assert_array_equal(ep.actions, episodes[i].actions)
        np.testing.assert_allclose(ep.infos["x_velocity"], episodes[i].infos["x_velocity"])
    from minari import MinariDataset

    meta = list(
        MinariDataset(root / "t/hopper/settled-v0/data").storage.get_episode_metadata(range(len(expected)))
    )
    assert [m["source_episode"] for m in meta] == expected
    assert [m["policy"] for m in meta] == [plan[i][0] for i in expected]
    slow = next(r for r in res.rows if r["name"] == "low")
    assert (slow["rest"], slow["pool"], slow["pool_kept"]) == (12, 6, 3)


def test_a_tighter_tolerance_or_a_later_span_changes_what_is_kept(source):
    root, _, plan = source
    # Over [150, 240) the late brakers have settled too: nothing is dropped.
    res = settle_filter(
        SettleConfig("t/hopper/src-v0", "t/hopper/late-v0", span=(150, 240), data_dir=root, k=2)
    )
    assert res.kept == len(plan)
    # A span longer than the episodes measures nothing: every pool-started episode is dropped.
    res = settle_filter(
        SettleConfig("t/hopper/src-v0", "t/hopper/long-v0", span=(50, 500), data_dir=root, k=2)
    )
    assert res.kept == sum(p[1] is None for p in plan)


@pytest.mark.parametrize(
    "out_id, span, scale",
    [
        ("t/b-v0", (200, 50), 1.0),
        ("t/b-v0", (-1, 5), 1.0),
        ("t/b-v0", (50, 200), 0.0),
        ("t/b-0.5-v0", (50, 200), 1.0),
    ],
)
def test_the_config_refuses_bad_spans_scales_and_ids(out_id, span, scale):
    with pytest.raises(ValueError):
        SettleConfig("a", out_id, span=span, tolerance_scale=scale)


def test_the_cli_prints_what_it_kept_and_refuses_a_bad_span(source):
    root, _, _ = source
    app = typer.Typer()
    app.command()(main)  # as `python -m research.settle` runs it
    args = ["t/hopper/src-v0", "--out-id", "t/hopper/cli-v0", "--data-dir", str(root), "--k", "2"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    assert "3/6" in r.output and "23 of 26 episodes" in r.output
    r = CliRunner().invoke(app, [*args[:3], "--span", "200:50", *args[3:]])
    assert r.exit_code != 0 and "span" in r.output
    r = CliRunner().invoke(app, [*args[:1], "--out-id", "t/hopper/x-0.5-v0", *args[3:]])
    assert r.exit_code != 0 and "Malformed dataset ID" in r.output
