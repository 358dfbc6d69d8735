"""datagen/breakout_dagger.py on the shipped five-goal Breakout model: a rollout records the teacher's labels on the
states the model reached (replaying its executed actions reproduces its frames), and a merge keeps the base
dataset's relabelled goals and gives each rollout episode its commanded goal."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ale_py")
pytest.importorskip("cv2")

from gmt.common.envs import make_env  # noqa: E402
from gmt.datagen.breakout import LEVELS, CollectConfig, TrackingAgent, collect_breakout, read_ram  # noqa: E402
from gmt.datagen.breakout_dagger import collect, merge, parse_goals  # noqa: E402
from gmt.model.checkpoint import load_checkpoint, model_info  # noqa: E402
from gmt.model.data.minari_io import load_dataset  # noqa: E402
from gmt.model.data.relabel import GoalTable  # noqa: E402

CKPT = Path(__file__).resolve().parents[2] / "checkpoints" / "breakout5-gmt"


def test_bad_goals_and_seed_counts_are_refused_with_the_reason():
    assert parse_goals(["4=lead4", "0=lead170"]) == {4: "lead4", 0: "lead170"}
    with pytest.raises(ValueError, match="GOAL=LEVEL"):
        parse_goals(["lead4"])
    with pytest.raises(ValueError, match="unknown level 'nope'"):
        parse_goals(["1=nope"])
    with pytest.raises(
        ValueError, match="seeds must be 1-1000"
    ):  # goal g's seeds would run into goal g + 1's
        collect(str(CKPT), {1: "strong"}, 1001, "test/x-v1", progress=False)


def test_rollouts_record_the_teachers_labels_on_the_models_states_and_merge_keeps_goals(
    tmp_path, monkeypatch
):
    monkeypatch.setenv("GMT_DATA_DIR", str(tmp_path))
    res = collect(
        str(CKPT),
        {1: "strong", 0: "slow168"},
        1,
        "test/dagger-v1",
        action_mode="argmax",
        steps=80,
        progress=False,
    )
    assert set(res["goals"]) == {"1", "0"}
    ds = load_dataset("test/dagger-v1", tmp_path)
    assert len(ds.episodes) == 2
    spec = model_info(load_checkpoint(str(CKPT)))
    for ep, level, goal in zip(ds.episodes, ("strong", "slow168"), (1, 0), strict=True):
        executed = ep.infos["executed_action"].astype(int)
        assert 0 < len(ep) <= 80 and len(executed) == len(ep)
        # replay what the game got from the same seed: the same frames, and the level's own choice on each
        env = make_env(spec, max_steps=80)
        obs, _ = env.reset(seed=10_000 + 1000 * goal)
        teacher = TrackingAgent(LEVELS[level])
        for t in range(len(ep)):
            np.testing.assert_array_equal(obs, ep.observations[t])
            assert teacher.decide(read_ram(env), np.random.default_rng(0)) == ep.actions[t]
            teacher.played(int(executed[t]))
            obs, *_ = env.step(int(executed[t]))
        env.close()
    # labels and played actions differ somewhere: the model is not its teacher
    assert (ds.episodes[0].actions != ds.episodes[0].infos["executed_action"]).any() or (
        ds.episodes[1].actions != ds.episodes[1].infos["executed_action"]
    ).any()

    collect_breakout(
        CollectConfig(
            episodes={"random": 1, "weak": 1, "good": 1, "strong": 1},
            max_steps=400,
            dataset_id="test/base-v1",
            data_dir=tmp_path,
        ),
        progress=False,
    )
    # the base, the rollouts (their commanded goals), then the base again as a scripted part (nearest goal)
    out = merge(
        "test/base-v1",
        ["test/dagger-v1", "test/base-v1"],
        "test/merged-v1",
        "return",
        2,
        0,
        str(tmp_path / "labels.json"),
    )
    assert out["episodes"] == 10 and out["rollout_episodes_per_goal"][:2] != [0, 0]
    table = GoalTable.load(tmp_path / "labels.json")
    base_goals = list(table.labels[:4])
    assert len(set(base_goals)) == 2  # both goals occur in the base
    assert list(table.labels[4:6]) == [1, 0]
    assert list(table.labels[6:]) == base_goals
    merged = load_dataset("test/merged-v1", tmp_path)
    base = load_dataset("test/base-v1", tmp_path)
    assert len(merged.episodes) == 10
    for a, b in zip(merged.episodes, [*base.episodes, *ds.episodes, *base.episodes], strict=True):
        np.testing.assert_array_equal(a.observations, b.observations)
        np.testing.assert_array_equal(a.actions, b.actions)
        assert ("executed_action" in a.infos) == ("executed_action" in b.infos)
    with pytest.raises(ValueError, match="only the return statistic"):
        merge(
            "test/base-v1",
            ["test/dagger-v1"],
            "test/bad-v1",
            "mean_x_velocity",
            2,
            0,
            str(tmp_path / "bad.json"),
        )
    assert not (tmp_path / "test" / "bad-v1").exists()
