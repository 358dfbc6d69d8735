"""The native incremental step (`model/native/gmt_step.c`) against the torch step it replaces."""

from __future__ import annotations

import os
import shutil
import time

import numpy as np
import pytest
import torch
from random_models import random_window_model

from gmt.model.engine import PolicyEngine
from gmt.model.fixtures import tiny_checkpoint
from gmt.model.kv_cache import KVCache
from gmt.model.native import NativeStep, load

if shutil.which(os.environ.get("CC", "cc")) is None:  # pragma: no cover - CI has a C compiler
    pytest.skip("no C compiler: the engine uses the torch step", allow_module_level=True)


@pytest.mark.parametrize(
    "discrete, n_head, n_embd", [(False, 1, 32), (True, 4, 64), (False, 2, 40), (True, 3, 24)]
)
def test_native_step_matches_the_torch_step(discrete, n_head, n_embd):
    """Same keys, values and predictions (fp32 rounding) over 40 steps past the window, with blends and
    scattered slots; widths that are and are not multiples of the kernel's 16 lanes."""
    model = random_window_model(discrete, n_head, n_embd)
    cfg = model.cfg
    lib = load()
    assert lib is not None
    native = NativeStep(model, lib)
    ref_cache, nat_cache = KVCache(cfg, 9), KVCache(cfg, 9)
    slots = np.array([7, 0, 4, 2])
    B = len(slots)
    rng = np.random.default_rng(1)
    prev = np.zeros(B, np.int64) if discrete else np.zeros((B, 5), np.float32)
    moved = 0.0
    with torch.inference_mode():
        for t in range(40):
            states = rng.normal(size=(B, 11)).astype(np.float32)
            goals = rng.integers(0, 4, B)
            blend_to = rng.integers(0, 4, B)
            blend_w = (rng.random(B) * (rng.random(B) < 0.4)).astype(np.float32)
            ts = np.full(B, t)
            ref = model.step(
                torch.from_numpy(prev),
                torch.from_numpy(goals),
                torch.from_numpy(states),
                torch.from_numpy(ts),
                ref_cache,
                torch.from_numpy(slots),
                torch.from_numpy(blend_to),
                torch.from_numpy(blend_w),
            ).numpy()
            out = native(prev, goals, states, ts, nat_cache, slots, blend_to, blend_w)
            np.testing.assert_allclose(out, ref, atol=1e-5, rtol=0)
            moved = max(moved, float(np.abs(out[0] - out[1]).max()))
            prev = out.argmax(1) if discrete else out
    torch.testing.assert_close(nat_cache.k, ref_cache.k, atol=1e-5, rtol=0)
    torch.testing.assert_close(nat_cache.v, ref_cache.v, atol=1e-5, rtol=0)
    assert torch.equal(nat_cache.tok, ref_cache.tok)
    assert moved > 1e-3  # the rows are not trivially equal


def test_engine_uses_the_native_step_unless_told_not_to():
    ckpt = tiny_checkpoint(attention="window")
    assert PolicyEngine(ckpt).describe().kernel == "native"
    assert PolicyEngine(ckpt, native=False).describe().kernel == "torch"
    assert PolicyEngine(tiny_checkpoint(attention="full")).describe().kernel == "torch"  # recompute path


def test_native_and_torch_kernels_agree_in_the_engine():
    ckpt = tiny_checkpoint(attention="window", calibrated=True)
    a, b = PolicyEngine(ckpt), PolicyEngine(ckpt, native=False)
    ca, cb = a.new_context(1, seed=3), b.new_context(1, seed=3)
    rng = np.random.default_rng(0)
    for t in range(30):
        if t == 10:
            a.set_goal(ca, 2, blend_steps=5)
            b.set_goal(cb, 2, blend_steps=5)
        obs = rng.normal(size=17)
        (x,), (y,) = a.act([ca], [obs]), b.act([cb], [obs])
        np.testing.assert_allclose(x, y, atol=1e-5, rtol=0)


class _CountingLib:
    """A native library whose `gmt_act` calls are recorded (rows per call) and passed on."""

    def __init__(self, lib) -> None:
        self._lib, self.rows = lib, []

    def __getattr__(self, name):
        return getattr(self._lib, name)

    def gmt_act(self, model, pool, rows, *rest):
        self.rows.append(rows)
        return self._lib.gmt_act(model, pool, rows, *rest)


@pytest.mark.parametrize(
    "threads, rows, parts", [(2, 64, [32, 32]), (3, 100, [33, 33, 34]), (4, 70, [35, 35])]
)
def test_a_pass_split_between_threads_is_the_pass_in_one_call(threads, rows, parts):
    """`act(threads=n)` splits the rows into parts of at least ROWS_PER_THREAD (70 rows: two parts, not four), one
    native call each, run at once: the answers and every session's later answers (its pool slot, key/value cache)
    are the same bit for bit, goal blends and sampled rows included."""
    ckpt = tiny_checkpoint(attention="window", calibrated=True)
    one, split = PolicyEngine(ckpt), PolicyEngine(ckpt)
    assert split.describe().kernel == "native"
    split._native._lib = counting = _CountingLib(split._native._lib)
    ctx_one = [one.new_context(i % 3, seed=i) for i in range(rows)]
    ctx_split = [split.new_context(i % 3, seed=i) for i in range(rows)]
    rng = np.random.default_rng(7)
    for t in range(6):
        if t == 2:
            for e, c in ((one, ctx_one), (split, ctx_split)):
                e.set_goal(c[5], 2, blend_steps=3)
        obs = [rng.normal(size=17) for _ in range(rows)]
        counting.rows.clear()
        a, b = one.act(ctx_one, obs), split.act(ctx_split, obs, threads=threads)
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
        assert sorted(counting.rows) == parts
    for name in ("step", "goal", "h_goal", "h_state", "h_action"):
        np.testing.assert_array_equal(getattr(one.pool, name), getattr(split.pool, name))
    assert torch.equal(one.pool.cache.k, split.pool.cache.k) and torch.equal(
        one.pool.cache.v, split.pool.cache.v
    )


def test_native_sampling_noise_is_the_numpy_construction():
    from gmt.model import native, sampling

    seed = np.array([0, 7, 2**63 + 5, 2**64 - 1], np.uint64)
    step = np.array([0, 1, 999, 2**40])
    for stream in (0, 1, 2):
        assert np.array_equal(
            native.uniforms(seed, step, 6, stream), sampling.numpy_uniforms(seed, step, 6, stream)
        )
    np.testing.assert_allclose(
        native.normals(seed, step, 6), sampling.numpy_normals(seed, step, 6), rtol=1e-12
    )


def test_discrete_window_model_acts_alike_on_both_kernels():
    """Discrete actions: the native step feeds the torch-free step ids back; every mode picks what the torch
    step's engine picks (logits agree to rounding, far below the gaps between them)."""
    ckpt = tiny_checkpoint(env_id="CartPole-v1", attention="window")
    a, b = PolicyEngine(ckpt), PolicyEngine(ckpt, native=False)
    assert a.describe().kernel == "native" and b.describe().kernel == "torch"
    rng = np.random.default_rng(4)
    for mode in ("argmax", "sample", "expert"):
        ca, cb = a.new_context(1, action_mode=mode, seed=5), b.new_context(1, action_mode=mode, seed=5)
        for _ in range(25):
            obs = rng.normal(size=4)
            assert a.act([ca], [obs]) == b.act([cb], [obs])


@pytest.mark.parametrize("move_at", [3, 40])
def test_a_session_rebuilt_from_its_stored_form_continues_bit_for_bit(move_at):
    """A session moved to another engine (its cache replayed from the stored steps) acts exactly as the
    same session left in place, early (history shorter than the receptive field) and late (longer)."""
    from gmt.bench.harness import default_size_checkpoint

    ckpt = default_size_checkpoint(None, K=5)  # 3 x 128: wide enough that a last-bit difference shows
    stay, src, dst = PolicyEngine(ckpt), PolicyEngine(ckpt), PolicyEngine(ckpt)
    assert stay.pool.H == 3 * 4 + 1 < 40
    a, b = stay.new_context(1, seed=9), src.new_context(1, seed=9)
    rng = np.random.default_rng(3)
    for t in range(move_at + 30):
        if t == move_at:
            stored = b.to_stored()
            src.release(b)
            dst.new_context(0)  # the moved session lands in another slot
            b = dst.from_stored(stored)
        if t == move_at - 2:  # a blend in flight across the move
            stay.set_goal(a, 2, blend_steps=4)
            (src if t < move_at else dst).set_goal(b, 2, blend_steps=4)
        obs = rng.normal(size=17)
        (x,) = stay.act([a], [obs])
        (y,) = (src if t < move_at else dst).act([b], [obs])
        assert np.array_equal(x, y), t


def test_sessions_adopted_together_are_replayed_together_and_continue_bit_for_bit(monkeypatch):
    """Six sessions of different ages (shorter and longer than the receptive field, one mid-blend, one never
    stepped) move to another engine and act there in one batch: their caches are replayed in one batched call per
    stored step, and every action is the one of the same session left in place."""
    from gmt.bench.harness import default_size_checkpoint
    from gmt.model.predict import Predictor

    ckpt = default_size_checkpoint(None, K=5)
    stay, dst = PolicyEngine(ckpt), PolicyEngine(ckpt)
    H = stay.pool.H  # 13
    ages = [0, 1, 4, H - 1, H + 7, 40]
    here = [stay.new_context(i % 3, seed=i) for i in range(len(ages))]
    rng = np.random.default_rng(4)
    for t in range(max(ages)):
        if t == 36:
            stay.set_goal(here[5], 2, blend_steps=6)  # still blending when it moves
        acting = [c for c, age in zip(here, ages, strict=True) if t >= max(ages) - age]
        stay.act(acting, list(rng.normal(size=(len(acting), 17))))
    replays = []
    real = Predictor.rebuild_caches
    monkeypatch.setattr(
        Predictor, "rebuild_caches", lambda self, slots: (replays.append(list(slots)), real(self, slots))
    )
    dst.new_context(0)  # the moved sessions land in other slots than they had
    moved = [dst.from_stored(c.to_stored(), key=f"m{i}") for i, c in enumerate(here)]
    for t in range(8):
        obs = list(rng.normal(size=(len(ages), 17)))
        want, got = stay.act(here, obs), dst.act(moved, obs)
        for i, (x, y) in enumerate(zip(want, got, strict=True)):
            assert np.array_equal(x, y), (t, ages[i])
    assert replays == [[c.slot for c in moved]]  # one replay of all six, at their first step


def test_the_pool_grows_safely_while_acts_run_in_another_thread():
    """New sessions (the pool doubling) arrive on one thread while another acts: every act commits to the
    arrays in use (the engine lock orders them); before the lock the native step wrote into freed arrays."""
    import threading

    from gmt.bench.harness import default_size_checkpoint

    engine = PolicyEngine(default_size_checkpoint(None, K=20), n_slots=16)
    ctxs = [engine.new_context(1, seed=i) for i in range(16)]
    obs = [engine.prepare_observation(np.random.default_rng(i).normal(size=17)) for i in range(16)]
    rounds, stop = [0], threading.Event()

    def acting():
        while not stop.is_set():
            engine.act(ctxs, obs, True)
            rounds[0] += 1

    def acted_since(n: int) -> None:  # the worker has acted again (a deadline, not a sleep)
        deadline = time.monotonic() + 60
        while rounds[0] <= n and time.monotonic() < deadline and worker.is_alive():
            time.sleep(0.001)
        assert rounds[0] > n, "the acting thread made no progress"

    worker = threading.Thread(target=acting)
    worker.start()
    try:
        while engine.pool.n_slots < 128:  # 16 -> 128: three doublings, each while the worker acts
            acted_since(rounds[0])
            engine.new_context(0)
        acted_since(rounds[0])
    finally:
        stop.set()
        worker.join()
    assert rounds[0] > 0
    assert all(c.step == rounds[0] for c in ctxs)


@pytest.mark.parametrize(
    "field, value",
    [("goals", 7), ("goals", -40), ("blend_to", 5), ("blend_w", float("nan")), ("actions", 9)],
)
def test_a_corrupt_stored_context_is_refused_not_embedded(field, value):
    """Ids from a store record are checked before any table lookup (the native step does no bounds check)."""
    discrete = field == "actions"
    ckpt = tiny_checkpoint(env_id="CartPole-v1" if discrete else "HalfCheetah-v5", attention="window")
    engine = PolicyEngine(ckpt)
    ctx = engine.new_context(1)
    obs_dim = 4 if discrete else 17
    for _ in range(5):
        engine.act([ctx], [np.zeros(obs_dim)])
    stored = ctx.to_stored()
    bad = getattr(stored, field).copy()
    bad[1] = value
    if field == "blend_to":
        w = stored.blend_w.copy()
        w[1] = 0.5
        stored = stored.__class__(**{**vars(stored), "blend_w": w})
    stored = stored.__class__(**{**vars(stored), field: bad})
    with pytest.raises(ValueError, match="stored"):
        engine.from_stored(stored, key="moved")


def test_the_library_cache_key_names_the_cpus_features(monkeypatch):
    """A build for one CPU (-march=native) is never handed to a CPU with other features from a shared cache."""
    import gmt.model.native as native

    monkeypatch.setattr(native, "_cpu_features", lambda: "avx2 fma sse4_2")
    here = native.library_key("cc")
    assert native.library_key("cc") == here  # stable for one machine
    monkeypatch.setattr(native, "_cpu_features", lambda: "avx2 avx512f fma sse4_2")
    assert native.library_key("cc") != here
    assert native.library_key("gcc") != native.library_key("cc")


def test_the_cpu_features_are_read_from_this_machine():
    import gmt.model.native as native

    feats = native._cpu_features()
    if os.path.exists("/proc/cpuinfo") and "flags" in open("/proc/cpuinfo").read():
        assert feats and feats.split() == sorted(feats.split())
