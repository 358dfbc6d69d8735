"""From served sessions to training data and back (issue 39): real HalfCheetah-v5 episodes driven through a real
server by `gmt run --record` with random goal schedules; `gmt data import-sessions` makes a Minari dataset that
`minari` loads, with per-step goal labels from the timelines; `gmt data describe` counts its goal switches;
`gmt train` runs on it; `gmt replay` of the recordings against their own checkpoint reproduces every action
(difference 0) and against another checkpoint does not."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from service_harness import RunningServer, make_settings

from gmt.client.rest import RestClient
from gmt.client.runner import RunConfig, run
from gmt.common.recording import RecordingError, find_recordings, read_recording
from gmt.model.fixtures import tiny_checkpoint

MODEL = "tiny-window"
STEPS, EPISODES = 60, 3
GMT = str(Path(sys.executable).parent / "gmt")


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """Recordings of EPISODES HalfCheetah-v5 episodes (random goal every 5..20 steps), and the checkpoints."""
    root = tmp_path_factory.mktemp("ckpt")
    tiny_checkpoint(root / MODEL, name=MODEL, attention="window", calibrated=True)
    other = tmp_path_factory.mktemp("other") / "tiny-other"
    tiny_checkpoint(other, name="tiny-other", attention="window", calibrated=True, seed=1)
    rec_dir = tmp_path_factory.mktemp("recordings")
    server = RunningServer(make_settings(checkpoints=[root], record_dir=rec_dir)).start()
    try:
        with RestClient(server.url) as client:
            cfg = RunConfig(
                model=MODEL, episodes=EPISODES, steps=STEPS, seed=3, record=True, random_schedule=(5, 20)
            )
            results = run(client, cfg, echo=lambda _: None)
    finally:
        server.stop()
    return rec_dir, root / MODEL, other, results


def _gmt(*args: str, data_dir: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "GMT_DATA_DIR": str(data_dir)}
    return subprocess.run([GMT, *args], capture_output=True, text=True, env=env, timeout=600)


def test_recordings_hold_the_episodes_as_the_client_saw_them(served):
    rec_dir, _, _, results = served
    files = find_recordings([rec_dir])
    assert len(files) == EPISODES
    by_id = {read_recording(f).meta["session_id"]: read_recording(f) for f in files}
    for res in results:
        rec = by_id[res.session_id]
        (ep,) = rec.episodes()
        assert len(ep) == STEPS and ep.truncated and not ep.terminated  # the time limit, reported
        assert rec.steps == STEPS + 1  # the last act carried the final observation
        np.testing.assert_array_equal(ep.actions, np.stack(res.trace.action).astype(np.float32))
        np.testing.assert_array_equal(ep.goals, res.trace.goal)
        np.testing.assert_allclose(ep.rewards, res.trace.reward)
        assert ep.reported.all() and ep.switches >= 2 and "x_velocity" in ep.infos


def test_import_sessions_makes_a_minari_dataset_that_gmt_train_accepts(served, tmp_path):
    rec_dir, ckpt, _, results = served
    r = _gmt(
        "data", "import-sessions", str(rec_dir), "--out-id", "gmt/halfcheetah/served-v0", data_dir=tmp_path
    )
    assert r.returncode == 0, r.stderr
    assert f"{EPISODES} episodes" in r.stdout and f"{EPISODES * STEPS} transitions" in r.stdout

    import minari

    os.environ["MINARI_DATASETS_PATH"] = str(tmp_path)
    try:
        ds = minari.load_dataset("gmt/halfcheetah/served-v0")
    finally:
        del os.environ["MINARI_DATASETS_PATH"]
    assert ds.total_episodes == EPISODES and ds.total_steps == EPISODES * STEPS
    switches = 0
    for ep, res in zip(ds.iterate_episodes(), sorted(results, key=lambda x: x.session_id), strict=True):
        assert ep.observations.shape == (STEPS + 1, 17) and ep.actions.shape == (STEPS, 6)
        labels = ep.infos["goal"][1:]  # Minari's infos start with the reset's
        np.testing.assert_array_equal(labels, res.trace.goal)  # the goals the server answered each step with
        switches += int(np.count_nonzero(np.diff(labels)))
        assert np.isfinite(ep.infos["x_velocity"][1:]).all()
    assert switches >= 2 * EPISODES

    r = _gmt("data", "describe", "gmt/halfcheetah/served-v0", data_dir=tmp_path)
    assert r.returncode == 0, r.stderr
    assert f"goal switches: {switches} in {EPISODES} of {EPISODES} episodes" in r.stdout

    out = tmp_path / "trained"
    r = _gmt(
        "train",
        "--dataset",
        "gmt/halfcheetah/served-v0",
        "--out",
        str(out),
        *("--steps", "2", "--batch-size", "4", "--n-layer", "1", "--n-embd", "32", "--context-length", "5"),
        *("--threads", "1", "--no-bf16", "--calibration-batches", "100", "--attention", "window"),
        data_dir=tmp_path,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"{switches} goal switches" in r.stdout
    meta = json.loads((out / "gmt.json").read_text())
    assert meta["dataset"]["transitions"] == EPISODES * STEPS and meta["goal_labels"]["source"] == "timeline"
    assert [g["name"] for g in meta["goals"]] == [
        g["name"] for g in json.loads((ckpt / "gmt.json").read_text())["goals"]
    ]


def test_replay_reproduces_its_own_checkpoint_exactly_and_measures_another(served, tmp_path):
    rec_dir, ckpt, other, _ = served
    own, diff = tmp_path / "own.json", tmp_path / "other.json"
    r = _gmt("replay", str(rec_dir), "--checkpoint", str(ckpt), "--json", str(own), data_dir=tmp_path)
    assert r.returncode == 0, r.stderr
    s = json.loads(own.read_text())["summary"]
    assert (
        s["value"] == 0.0
        and s["max_abs_diff"] == 0.0
        and s["exact_steps"] == s["steps"] == EPISODES * (STEPS + 1)
    )
    assert s["changes"] >= 2 * EPISODES and s["before"] == s["after"] == 0.0

    r = _gmt(
        "replay",
        str(rec_dir),
        "--checkpoint",
        str(other),
        "--json",
        str(diff),
        "--plot",
        str(tmp_path / "p.png"),
        data_dir=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    body = json.loads(diff.read_text())
    assert body["summary"]["value"] > 0.01 and body["summary"]["exact_steps"] == 0
    assert len(body["per_step"]) == EPISODES * (STEPS + 1) and (tmp_path / "p.png").stat().st_size > 0
    assert all(
        c["before"] is not None and c["after"] > 0
        for e in body["episodes"]
        for c in e["changes"]
        if c["step"] >= 1
    )

    r = _gmt("replay", str(tmp_path / "nothing-here"), "--checkpoint", str(ckpt), data_dir=tmp_path)
    assert r.returncode == 2 and "no such recording" in r.stderr


def _offline(data_dir: Path, dataset_id: str, speeds: list[float]) -> None:
    """A small HalfCheetah-shaped dataset whose episode i moves at speeds[i] m/s throughout."""
    import gymnasium as gym

    from gmt.model.data.minari_io import Episode, write_dataset

    rng = np.random.default_rng(5)
    env = gym.make("HalfCheetah-v5")
    eps = [
        Episode(
            observations=rng.normal(size=(20, 17)),
            actions=rng.uniform(-1, 1, (20, 6)).astype(np.float32),
            rewards=np.full(20, v, np.float32),
            terminated=False,
            truncated=True,
            infos={"x_velocity": np.full(20, v)},
            final_observation=rng.normal(size=17),
            episode_id=i,
        )
        for i, v in enumerate(speeds)
    ]
    write_dataset(dataset_id, eps, "HalfCheetah-v5", env.observation_space, env.action_space, data_dir)
    env.close()


def test_import_sessions_includes_offline_data_whose_goals_are_the_served_models(served, tmp_path):
    from gmt.model.data.minari_io import load_dataset
    from gmt.model.data.served import import_sessions, step_labels

    rec_dir = served[0]
    _offline(tmp_path, "test/cheetah/offline-v0", [0.0, 0.0005, 1.0, 1.0005, 2.0, 2.0005])
    res = import_sessions([rec_dir], "test/cheetah/both-v0", tmp_path, include="test/cheetah/offline-v0")
    assert (res.episodes, res.included, res.transitions) == (EPISODES + 6, 6, EPISODES * STEPS + 120)
    labels, goals = step_labels(load_dataset("test/cheetah/both-v0", tmp_path))
    assert [g["name"] for g in goals] == ["low", "medium", "high"]
    assert [lab.tolist() for lab in labels[EPISODES:]] == [[g] * 20 for g in (0, 0, 1, 1, 2, 2)]
    # An offline dataset whose goals mean other speeds would give the labels another meaning: refused.
    _offline(tmp_path, "test/cheetah/faster-v0", [0.0, 0.0005, 1.5, 1.5005, 3.0, 3.0005])
    with pytest.raises(ValueError, match="would not mean the same goals"):
        import_sessions([rec_dir], "test/cheetah/both-v1", tmp_path, include="test/cheetah/faster-v0")


@pytest.mark.parametrize(
    "name, content, words",
    [
        ("a.npz", b"just text\n", "not an .npz archive"),  # np.load's own words invite allow_pickle=True
        ("b.npz", b"PK\x03\x04truncated", "not a recording .npz"),  # was zipfile.BadZipFile, a traceback
        ("c.json", b"{not json", "is not a recording's JSON"),
    ],
)
def test_a_file_that_is_not_a_recording_is_named_and_refused(tmp_path, name, content, words):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(RecordingError, match=words) as e:
        read_recording(tmp_path / name)
    assert name in str(e.value) and "pickle" not in str(e.value)


def test_gmt_data_import_takes_a_folder_of_recordings_as_import_sessions_does(served, tmp_path):
    from gmt.model.data.importer import import_data
    from gmt.model.data.minari_io import load_dataset
    from gmt.model.data.served import import_sessions

    rec_dir = served[0]
    rep = import_data(rec_dir, "test/cheetah/imported-v0", None, tmp_path)
    import_sessions([rec_dir], "test/cheetah/sessions-v0", tmp_path)
    assert rep.kind == "sessions" and rep.episodes == EPISODES and "x_velocity" in rep.info_keys
    a, b = (
        load_dataset("test/cheetah/imported-v0", tmp_path),
        load_dataset("test/cheetah/sessions-v0", tmp_path),
    )
    assert a.fingerprint == b.fingerprint and a.goal_labels == b.goal_labels
