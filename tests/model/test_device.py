"""`PolicyEngine(device=...)` (`gmt serve --device`): the torch step on a device, with the key/value pool allocated
there, answers as the default CPU path (the native step) does, within 1e-5 (fp32; the two sum in different
orders). On a machine without a GPU the same code runs with device `cpu` (every tensor still goes through the
device transfers, which are no-ops there); with a GPU, `cuda` runs too."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gmt.model.engine import PolicyEngine, resolve_device
from gmt.model.fixtures import tiny_checkpoint
from gmt.service.registry import engine_for

DEVICES = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]
TOLERANCE = 1e-5  # docs/performance.md: the device path against the native step, per action component


def _window():
    return tiny_checkpoint(attention="window", calibrated=True)  # same weights every call (seeded)


@pytest.mark.parametrize("device", DEVICES)
def test_the_device_step_answers_as_the_default_cpu_path(device):
    """Six sessions acting in batches (sampled actions), a gradual goal switch, a reset, and a session moved to
    another engine through its stored form (its cache rebuilt by the device path's reference forward)."""
    default = PolicyEngine(_window())
    on_device = PolicyEngine(_window(), device=device, native=False, n_slots=8)
    assert default.describe().kernel == "native" and on_device.describe().kernel == "torch"
    assert on_device.pool.cache.k.device.type == device
    a = [default.new_context(i % 3, seed=i) for i in range(6)]
    b = [on_device.new_context(i % 3, seed=i) for i in range(6)]
    rng = np.random.default_rng(5)
    for t in range(20):
        if t == 6:
            default.set_goal(a[1], 2, blend_steps=4)
            on_device.set_goal(b[1], 2, blend_steps=4)
        if t == 9:
            default.reset(a[2], 0)
            on_device.reset(b[2], 0)
        if t == 12:  # session 3 continues on a fresh engine of the same device
            moved = PolicyEngine(_window(), device=device, native=False)
            b[3] = moved.from_stored(b[3].to_stored(), key="moved")
        obs = rng.normal(size=(6, 17))
        want = default.act(a, list(obs))
        got = [*on_device.act(b[:3], list(obs[:3]))]
        got += (moved if t >= 12 else on_device).act([b[3]], [obs[3]])
        got += on_device.act(b[4:], list(obs[4:]))
        for i, (x, y) in enumerate(zip(want, got, strict=True)):
            np.testing.assert_allclose(y, x, atol=TOLERANCE, rtol=0, err_msg=f"step {t}, session {i}")


@pytest.mark.parametrize("device", DEVICES)
def test_a_served_engine_off_the_cpu_allocates_its_pool_up_front(device):
    engine = engine_for(_window(), device=device, n_slots=64)
    if device == "cpu":  # the default path: the native step, a pool that grows from 16 slots
        assert engine.describe().kernel == "native" and engine.pool.n_slots == 16
    else:
        assert engine.describe().kernel == "torch" and engine.pool.n_slots == 64


def test_device_names():
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="device must be one of cpu, cuda, auto"):
        resolve_device("tpu")
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match="the native step runs on the CPU"):
            PolicyEngine(_window(), device="cuda", native=True)
    else:
        with pytest.raises(ValueError, match="torch sees no CUDA GPU here"):
            PolicyEngine(_window(), device="cuda")


@pytest.mark.parametrize("device", DEVICES)
def test_a_warm_up_leaves_no_session_behind_and_changes_no_answer(device):
    """`engine_for` warms a device engine up with one throwaway act: its slot is free again and the next session
    answers exactly as on an engine that was never warmed up."""
    warmed = PolicyEngine(_window(), device=device, native=False, n_slots=4)
    cold = PolicyEngine(_window(), device=device, native=False, n_slots=4)
    warmed.warm_up()
    assert warmed.pool.live == 0 and sorted(warmed.pool.free) == [0, 1, 2, 3]
    a, b = warmed.new_context(1, seed=3), cold.new_context(1, seed=3)
    assert a.slot == b.slot  # the same slot, whose cache the warm-up wrote into
    obs = np.random.default_rng(2).normal(size=(8, 17))
    for o in obs:
        np.testing.assert_array_equal(warmed.act([a], [o])[0], cold.act([b], [o])[0])
