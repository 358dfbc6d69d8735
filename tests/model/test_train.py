"""Training lowers the loss, is deterministic and resumable; checkpoints round-trip exactly; pickle is refused."""

import json
import pickle

import gymnasium as gym
import numpy as np
import pytest
import torch

from gmt.model.checkpoint import META, WEIGHTS, CheckpointError, load_checkpoint, state_dicts_equal
from gmt.model.config import TrainConfig
from gmt.model.fixtures import SyntheticDataset, _Episode
from gmt.model.losses import gmt_loss
from gmt.model.tokens import WindowSampler
from gmt.model.train import RESUME_DIR, build_sampler, model_config_for, train

SMALL = {"context_length": 4, "n_layer": 1, "n_head": 1, "n_embd": 32}


def _tc(**kw):
    base = dict(
        steps=60,
        batch_size=16,
        lr=3e-3,
        warmup_steps=5,
        log_every=10,
        save_every=1000,
        seed=0,
        calibration_batches=5,
    )
    return TrainConfig(**{**base, **kw})


def _eval_loss(ckpt, ds):
    sampler, _, _ = build_sampler(ds, ds.labels, ckpt.config)
    w = sampler.windows(torch.arange(0, sampler.n, 7))
    with torch.inference_mode():
        pred, gl = ckpt.model(*w.model_inputs())
    return gmt_loss(pred, gl, w.actions, w.goals, w.valid, False).total.item()


def test_short_training_lowers_the_loss(tmp_path):
    ds = SyntheticDataset()
    cfg = model_config_for(ds, 3, **SMALL)
    from gmt.model.gmt import GMT

    torch.manual_seed(0)
    untrained = type("C", (), {"model": GMT(cfg).eval(), "config": cfg})()
    before = _eval_loss(untrained, ds)
    ckpt = train(ds, ds.labels, ds.goals, tmp_path / "c", _tc(steps=150), SMALL, progress=False)
    after = _eval_loss(ckpt, ds)
    assert after < 0.6 * before, (before, after)


def test_training_is_deterministic_under_a_seed(tmp_path):
    ds = SyntheticDataset()
    a = train(ds, ds.labels, ds.goals, tmp_path / "a", _tc(steps=20), SMALL, progress=False)
    b = train(ds, ds.labels, ds.goals, tmp_path / "b", _tc(steps=20), SMALL, progress=False)
    c = train(ds, ds.labels, ds.goals, tmp_path / "c", _tc(steps=20, seed=1), SMALL, progress=False)
    assert state_dicts_equal(a.model, b.model)
    assert not state_dicts_equal(a.model, c.model)


def test_resume_continues_exactly(tmp_path, monkeypatch):
    import gmt.model.train as train_module

    ds = SyntheticDataset()
    full = train(ds, ds.labels, ds.goals, tmp_path / "full", _tc(steps=30), SMALL, progress=False)
    # Interrupted run: killed just after its resume state was saved at step 20, then resumed to 30.
    save = train_module._save_resume

    def save_then_die(*args):
        save(*args)
        raise KeyboardInterrupt

    monkeypatch.setattr(train_module, "_save_resume", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        train(ds, ds.labels, ds.goals, tmp_path / "part", _tc(steps=30, save_every=20), SMALL, progress=False)
    monkeypatch.setattr(train_module, "_save_resume", save)
    assert (tmp_path / "part" / RESUME_DIR / "state.json").exists()
    assert not (tmp_path / "part" / META).exists()
    resumed = train(
        ds, ds.labels, ds.goals, tmp_path / "part", _tc(steps=30, save_every=20), SMALL, progress=False
    )
    assert state_dicts_equal(full.model, resumed.model)
    assert not (tmp_path / "part" / RESUME_DIR).exists()  # a finished run leaves nothing to resume


def test_init_from_starts_at_a_checkpoints_weights_and_refuses_another_shape(tmp_path):
    ds = SyntheticDataset()
    train(ds, ds.labels, ds.goals, tmp_path / "first", _tc(steps=150), SMALL, progress=False)
    scratch = _eval_loss(
        train(ds, ds.labels, ds.goals, tmp_path / "scratch", _tc(steps=3), SMALL, progress=False), ds
    )
    tuned = train(
        ds,
        ds.labels,
        ds.goals,
        tmp_path / "tuned",
        _tc(steps=3, init_from=str(tmp_path / "first")),
        SMALL,
        progress=False,
    )
    # three steps from the trained weights keep their low loss; three from random ones do not
    assert _eval_loss(tuned, ds) < 0.8 * scratch, (_eval_loss(tuned, ds), scratch)
    meta = json.loads((tmp_path / "tuned" / META).read_text())
    assert meta["init_from"]["fingerprint"] == load_checkpoint(tmp_path / "first").fingerprint
    assert meta["training"]["init_from"] == str(tmp_path / "first")
    with pytest.raises(CheckpointError, match=r"n_embd \(32 there, 16 here\)"):
        train(
            ds,
            ds.labels,
            ds.goals,
            tmp_path / "other",
            _tc(steps=3, init_from=str(tmp_path / "first")),
            {**SMALL, "n_embd": 16},
            progress=False,
        )


def test_checkpoint_round_trip_is_exact(tmp_path):
    ds = SyntheticDataset()
    ds.preprocessing = {"screen_size": 7}  # what a collector declared; the checkpoint carries it on
    ckpt = train(
        ds,
        ds.labels,
        ds.goals,
        tmp_path / "c",
        _tc(steps=5, default_action_mode="mean"),
        SMALL,
        progress=False,
    )
    loaded = load_checkpoint(tmp_path / "c")
    assert loaded.preprocessing == {"screen_size": 7} and loaded.default_action_mode == "mean"
    assert state_dicts_equal(ckpt.model, loaded.model)
    assert loaded.config == ckpt.config and loaded.goals == ckpt.goals and loaded.env_id == "HalfCheetah-v5"
    assert np.array_equal(loaded.obs_norm.mean, ckpt.obs_norm.mean)
    meta = json.loads((tmp_path / "c" / META).read_text())
    for key in (
        "format_version",
        "model",
        "env",
        "normalization",
        "statistic",
        "goals",
        "training",
        "dataset",
        "code_revision",
    ):
        assert key in meta
    obs = np.random.default_rng(0).normal(size=(3, 17)).astype(np.float32)
    assert np.array_equal(ckpt.obs_norm(obs), loaded.obs_norm(obs))
    assert ckpt.action_noise.shape == (3, 6) and np.array_equal(loaded.action_noise, ckpt.action_noise)


def test_malformed_action_noise_is_refused(tmp_path):
    ds = SyntheticDataset()
    train(ds, ds.labels, ds.goals, tmp_path / "c", _tc(steps=2), SMALL, progress=False)
    meta = json.loads((tmp_path / "c" / META).read_text())
    meta["action_noise"]["std"] = [[0.1, 0.2]]
    (tmp_path / "c" / META).write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match=r"action_noise.std must be \[3, 6\]"):
        load_checkpoint(tmp_path / "c")


def test_loading_refuses_pickle(tmp_path):
    ds = SyntheticDataset()
    train(ds, ds.labels, ds.goals, tmp_path / "c", _tc(steps=2), SMALL, progress=False)
    pkl = tmp_path / "model.pt"
    pkl.write_bytes(pickle.dumps({"weights": [1, 2, 3]}))
    with pytest.raises(CheckpointError, match="pickle"):
        load_checkpoint(pkl)
    # A pickle disguised as the weights file is refused before anything is deserialised.
    (tmp_path / "c" / WEIGHTS).write_bytes(pickle.dumps({"weights": [1, 2, 3]}))
    with pytest.raises(CheckpointError, match="pickle"):
        load_checkpoint(tmp_path / "c")


def test_missing_files_give_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match=f"has no {WEIGHTS}"):
        load_checkpoint(tmp_path)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "nope")


def test_window_model_trains_on_longer_sequences_and_records_its_span(tmp_path):
    ds = SyntheticDataset()
    window = {**SMALL, "attention": "window"}
    cfg = model_config_for(ds, 3, **window)
    assert _tc().sequence_steps(cfg) == 2 * cfg.context_length  # the window default: 2K
    with pytest.raises(ValueError, match="exactly K"):
        _tc(sequence_length=9).sequence_steps(model_config_for(ds, 3, **SMALL))
    from gmt.model.gmt import GMT

    torch.manual_seed(0)
    untrained = type("C", (), {"model": GMT(cfg).eval(), "config": cfg})()
    before = _eval_loss(untrained, ds)
    ckpt = train(ds, ds.labels, ds.goals, tmp_path / "w", _tc(steps=150), window, progress=False)
    assert _eval_loss(ckpt, ds) < 0.6 * before
    meta = json.loads((tmp_path / "w" / META).read_text())
    assert meta["model"]["attention"] == "window" and meta["training"]["sequence_length"] == 0
    assert load_checkpoint(tmp_path / "w").config.attention == "window"
    del meta["model"]["attention"]  # a checkpoint written before the field existed reads as full
    (tmp_path / "w" / META).write_text(json.dumps(meta))
    assert load_checkpoint(tmp_path / "w").config.attention == "full"


class _Frames:
    """A tiny image dataset: 4 x 36 x 36 uint8 frames (the smallest the Nature CNN takes) with a dot whose column tells the action."""

    def __init__(self, n_episodes: int = 6, length: int = 20) -> None:
        self.observation_space = gym.spaces.Box(0, 255, (4, 36, 36), np.uint8)
        self.action_space = gym.spaces.Discrete(4)
        self.env_id, self.dataset_id, self.fingerprint, self.preprocessing = "ALE/Breakout-v5", "f", "f", None
        rng = np.random.default_rng(0)
        self.labels = [i % 3 for i in range(n_episodes)]
        self.episodes = []
        for _ in self.labels:
            col = rng.integers(0, 36, size=length)
            obs = np.zeros((length, 4, 36, 36), np.uint8)
            obs[np.arange(length), :, 18, col] = 255
            self.episodes.append(_Episode(obs, (col // 9).astype(np.int64), np.ones(length, np.float32)))
        self.goals = SyntheticDataset().goals


def test_frame_augmentation_trains_reproducibly_and_only_on_images(tmp_path):
    ds = _Frames()
    tc = _tc(steps=4, augment_shift=2.0, augment_degrees=5.0)
    a = train(ds, ds.labels, ds.goals, tmp_path / "a", tc, SMALL, progress=False)
    b = train(ds, ds.labels, ds.goals, tmp_path / "b", tc, SMALL, progress=False)
    plain = train(ds, ds.labels, ds.goals, tmp_path / "p", _tc(steps=4), SMALL, progress=False)
    assert state_dicts_equal(a.model, b.model) and not state_dicts_equal(a.model, plain.model)
    assert a.meta["training"]["augment_shift"] == 2.0
    vec = SyntheticDataset()
    with pytest.raises(ValueError, match="image observations only"):
        train(vec, vec.labels, vec.goals, tmp_path / "v", tc, SMALL, progress=False)
    with pytest.raises(ValueError, match="augment_shift"):
        TrainConfig(augment_shift=-1)


def test_the_fine_image_encoder_learns_where_the_dot_is_and_round_trips(tmp_path):
    """`image_encoder="fine"` trains on frames, is saved with its kind, and its reload acts exactly alike."""
    ds = _Frames()
    fine = train(
        ds,
        ds.labels,
        ds.goals,
        tmp_path / "f",
        _tc(steps=120),
        {**SMALL, "image_encoder": "fine"},
        progress=False,
    )
    assert json.loads((tmp_path / "f" / META).read_text())["model"]["image_encoder"] == "fine"
    back = load_checkpoint(tmp_path / "f")
    assert back.config.image_encoder == "fine" and state_dicts_equal(back.model, fine.model)
    sampler, _, _ = build_sampler(ds, ds.labels, fine.config)
    w = sampler.windows(torch.arange(0, sampler.n))
    with torch.inference_mode():
        pred, _ = back.model(*w.model_inputs())
    accuracy = (pred.argmax(-1) == w.actions)[w.valid].float().mean().item()
    assert accuracy > 0.6, accuracy  # four actions: chance is 0.25
    with pytest.raises(ValueError, match="image_encoder must be nature or fine"):
        model_config_for(ds, 3, image_encoder="coarse")


def test_frames_are_held_once_the_sampler_is_built():
    """The dataset's episodes then read the sampler's one array of frames, and the arrays they were loaded into
    (T + 1 frames each, as `load_dataset` reads them, with a final observation viewing the last) are freed."""
    import gc
    import weakref

    ds = _Frames()
    loaded = []
    for ep in ds.episodes:  # as load_dataset leaves them: views of one array of T + 1 frames
        raw = np.concatenate([ep.observations, ep.observations[-1:] // 2])
        ep.observations, ep.final_observation = raw[:-1], raw[-1]
        loaded.append(weakref.ref(raw))
        del raw
    before = [(ep.observations.copy(), ep.final_observation.copy()) for ep in ds.episodes]
    cfg = model_config_for(ds, 3, **SMALL)
    sampler, _, _ = build_sampler(ds, ds.labels, cfg)
    gc.collect()
    assert all(ref() is None for ref in loaded)  # nothing keeps the loaded arrays alive
    frames = sampler.states.numpy()
    for ep, (obs, final) in zip(ds.episodes, before, strict=True):
        assert np.shares_memory(ep.observations, frames) and np.array_equal(ep.observations, obs)
        assert np.array_equal(ep.final_observation, final)
    assert frames.shape == (sum(len(ep.actions) for ep in ds.episodes), 4, 36, 36)
    w = sampler.windows(torch.tensor([len(ds.episodes[0].actions)]))  # the second episode's first step
    assert torch.equal(w.states[0, -1], torch.from_numpy(before[1][0][0]))
    with pytest.raises(ValueError, match="concatenated states"):
        WindowSampler(frames[:-1], [ep.actions for ep in ds.episodes], ds.labels, K=4)


def test_a_default_action_mode_the_model_cannot_serve_is_refused_before_training(tmp_path):
    ds = SyntheticDataset()  # continuous actions: sample or mean
    with pytest.raises(ValueError, match="default_action_mode 'expert'"):
        train(
            ds, ds.labels, ds.goals, tmp_path / "c", _tc(default_action_mode="expert"), SMALL, progress=False
        )
    assert not (tmp_path / "c" / META).exists()


def test_the_learning_rate_follows_the_time_limit_when_it_is_ahead_of_the_steps():
    from gmt.model.train import lr_at

    tc = _tc(steps=1000, warmup_steps=10, lr=1e-3, time_limit_s=60)
    floor = tc.lr * tc.min_lr_ratio
    assert lr_at(5, tc, 0.9) == pytest.approx(tc.lr * 6 / 10)  # warmup is counted in steps
    assert lr_at(10, tc, 0.0) == pytest.approx(tc.lr)
    assert lr_at(10, tc, 1.0) == pytest.approx(floor)  # the time is up: the floor, whatever the step
    assert lr_at(505, tc, 0.5) == pytest.approx(lr_at(505, tc, 0.0))  # the step share leads: unchanged
    assert lr_at(100, tc, 0.5) == pytest.approx(lr_at(505, tc, 0.0))  # the time share leads
    with pytest.raises(ValueError, match="time_limit_s"):
        _tc(time_limit_s=-1)


def test_a_time_limit_ends_training_early_and_records_the_steps_done(tmp_path):
    ds = SyntheticDataset()
    ckpt = train(
        ds, ds.labels, ds.goals, tmp_path / "t", _tc(steps=10**7, time_limit_s=0.5), SMALL, progress=False
    )
    info = json.loads((tmp_path / "t" / META).read_text())["training"]
    assert 1 <= info["steps_done"] < 10**7
    assert info["steps_done"] == ckpt.meta["training"]["steps_done"]
    assert info["wall_time_s"] < 60  # it stopped at the limit, not after ten million steps
    assert info["final"]["lr"] < 3e-3  # the schedule decayed with the elapsed time


def test_a_sampler_moved_to_another_device_gathers_its_windows_there():
    ds = SyntheticDataset()
    cfg = model_config_for(ds, 3, **SMALL)
    sampler, _, _ = build_sampler(ds, ds.labels, cfg)
    ends = torch.tensor([0, 5, sampler.n - 1])
    ref = sampler.windows(ends)
    # every tensor must move: one left behind would mix devices in the gather and raise
    meta = sampler.to(torch.device("meta")).windows(ends)
    for x, y in zip(meta.model_inputs(), ref.model_inputs(), strict=True):
        assert x.device.type == "meta" and x.shape == y.shape and x.dtype == y.dtype
