"""The native step's bfloat16 products (`NativeStep(bf16=True)`, `PolicyEngine(precision="bf16")`)."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
import torch
from random_models import random_window_model

from gmt.model import native
from gmt.model.engine import PolicyEngine
from gmt.model.fixtures import tiny_checkpoint
from gmt.model.gmt import GMT
from gmt.model.kv_cache import KVCache

if shutil.which(os.environ.get("CC", "cc")) is None:  # pragma: no cover - CI has a C compiler
    pytest.skip("no C compiler: the engine uses the torch step", allow_module_level=True)

needs_bf16 = pytest.mark.skipif(
    not native.has_bf16(), reason="this CPU has no AVX-512 BF16: the bfloat16 products are not built"
)


def _as_float(bits: np.ndarray) -> np.ndarray:
    return (bits.astype(np.uint32) << 16).view(np.float32)


def test_bf16_bits_round_to_nearest_even_and_flush_denormals():
    """What the kernel's conversion does (`vcvtne2ps2bf16`): torch's rounding on normal values, ties to even,
    denormals to a signed zero, NaN kept."""
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(size=1000) * 10.0 ** rng.integers(-30, 30, 1000)]).astype(np.float32)
    np.testing.assert_array_equal(
        _as_float(native.bf16_bits(x)), torch.from_numpy(x).bfloat16().float().numpy()
    )
    # 1 + 2^-8 lies half way between bf16's 1 and 1 + 2^-7: to the even one (1); 1 + 3 * 2^-8 goes up.
    ties = np.array([1 + 2**-8, 1 + 3 * 2**-8, -(1 + 2**-8)], np.float32)
    np.testing.assert_array_equal(_as_float(native.bf16_bits(ties)), [1.0, 1 + 2**-6, -1.0])
    special = _as_float(native.bf16_bits(np.array([1e-40, -1e-40, np.inf, np.nan], np.float32)))
    assert special[0] == 0 and not np.signbit(special[0]) and special[1] == 0 and np.signbit(special[1])
    assert special[2] == np.inf and np.isnan(special[3])


def test_bf16_packing_pairs_consecutive_rows_of_each_column():
    w = np.arange(6 * 40, dtype=np.float32).reshape(6, 40)  # small integers: exact in bfloat16
    packed = native.pack_bf16(w)  # [2 tiles, 3 pairs, 32]
    assert packed.shape == (2, 3, native.TILE)
    lo, hi = _as_float(packed & 0xFFFF), _as_float(packed >> 16)
    np.testing.assert_array_equal(lo[0], w[0::2, :32])
    np.testing.assert_array_equal(hi[1, :, :8], w[1::2, 32:])
    assert not hi[1, :, 8:].any()  # the padded columns are zero
    with pytest.raises(ValueError, match="even"):
        native.pack_bf16(np.zeros((5, 4), np.float32))


@needs_bf16
@pytest.mark.parametrize(("M", "K", "N"), [(1, 128, 384), (11, 72, 45), (19, 512, 128)])
def test_the_bf16_product_is_the_product_of_the_rounded_operands(M, K, N):
    """One block product (`gmt_linear`): the exact product of the bf16-rounded x and w, to fp32 summation error;
    not fp32's; a row alone the same bits as in its batch. Widths with and without a conversion tail, partial
    column tiles, 1 to 19 rows."""
    rng = np.random.default_rng(M)
    x = rng.normal(size=(M, K)).astype(np.float32)
    w = (rng.normal(size=(K, N)) * 0.1).astype(np.float32)
    b = rng.normal(size=N).astype(np.float32)
    y = native.linear(x, w, b, bf16=True)
    xr = _as_float(native.bf16_bits(x)).reshape(M, K).astype(np.float64)
    wr = _as_float(native.bf16_bits(w)).reshape(K, N).astype(np.float64)
    bound = np.abs(xr) @ np.abs(wr) * K * 2.0**-24 + np.abs(b) * 2.0**-24  # sequential fp32 sums
    assert np.all(np.abs(y - (xr @ wr + b)) <= bound)
    exact = x.astype(np.float64) @ w.astype(np.float64) + b
    assert np.abs(native.linear(x, w, b) - exact).max() * 10 < np.abs(y - exact).max()
    for r in (0, M - 1):
        np.testing.assert_array_equal(native.linear(x[r : r + 1], w, b, bf16=True)[0], y[r])


def _rounded(model: GMT) -> GMT:
    """The reference for the bf16 step: the blocks' four linears with weights and inputs rounded to bfloat16."""

    def to_bf16(t: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(_as_float(native.bf16_bits(t.detach().numpy()))).reshape(t.shape)

    for b in model.blocks:
        for lin in (b.attn.qkv, b.attn.proj, b.fc, b.out):
            lin.weight.data = to_bf16(lin.weight.data)
            lin.register_forward_pre_hook(lambda _m, args: (to_bf16(args[0]),))
    return model


@needs_bf16
@pytest.mark.parametrize("discrete, n_head, n_embd", [(False, 2, 64), (True, 4, 32), (False, 1, 40)])
def test_bf16_step_is_the_torch_step_with_its_products_rounded_to_bf16(discrete, n_head, n_embd):
    """The bf16 kernel's predictions are those of the torch step whose block products take bf16-rounded weights
    and inputs, mostly to fp32 rounding (where the two sum in another order, a value on a rounding boundary may
    round to the neighbouring bf16 value, which the later layers and the cache carry: some steps differ by up to
    ~2e-3), far nearer than to the fp32 kernel's;
    and they differ from the fp32 kernel's at every step. Widths that are and are not multiples of the
    conversion's 32 lanes."""
    model = random_window_model(discrete, n_head, n_embd)
    cfg = model.cfg
    lib = native.load()
    bf16, fp32 = native.NativeStep(model, lib, bf16=True), native.NativeStep(model, lib)
    ref_model = GMT(cfg).eval()
    ref_model.load_state_dict(model.state_dict())
    _rounded(ref_model)
    caches = {k: KVCache(cfg, 9) for k in ("ref", "bf16", "fp32")}
    slots = np.array([7, 0, 4, 2])
    B = len(slots)
    rng = np.random.default_rng(1)
    prev = np.zeros(B, np.int64) if discrete else np.zeros((B, 5), np.float32)
    to_ref, to_fp32 = [], []  # per step: the largest difference from each
    with torch.inference_mode():
        for t in range(30):
            states = rng.normal(size=(B, 11)).astype(np.float32)
            goals, blend_to = rng.integers(0, 4, B), rng.integers(0, 4, B)
            blend_w = (rng.random(B) * (rng.random(B) < 0.4)).astype(np.float32)
            ts = np.full(B, t)
            args = (prev, goals, states, ts)
            ref = ref_model.step(
                *(torch.from_numpy(a) for a in args),
                caches["ref"],
                torch.from_numpy(slots),
                torch.from_numpy(blend_to),
                torch.from_numpy(blend_w),
            ).numpy()
            out = bf16(*args, caches["bf16"], slots, blend_to, blend_w)
            exact = fp32(*args, caches["fp32"], slots, blend_to, blend_w)
            to_ref.append(float(np.abs(out - ref).max()))
            to_fp32.append(float(np.abs(out - exact).max()))
            prev = ref.argmax(1) if discrete else ref  # all three go on from the same actions
    to_ref, to_fp32 = np.array(to_ref), np.array(to_fp32)
    # How often a rounding flips depends on the summation order of torch's kernels on this CPU: loose bounds here,
    # the exact check is the product's own test above.
    assert np.median(to_ref) < 0.2 * np.median(to_fp32) and to_ref.max() < 5e-3
    assert to_fp32.min() > 1e-4


@needs_bf16
def test_a_bf16_engine_is_batch_invariant_and_near_the_fp32_engine():
    """A session's bf16 answers are the same bit for bit alone or in a batch of 20 sessions, and near fp32's."""
    ckpt = tiny_checkpoint(seed=3, attention="window", context_length=6)
    alone, crowded = PolicyEngine(ckpt, precision="bf16"), PolicyEngine(ckpt, precision="bf16")
    exact = PolicyEngine(ckpt)
    assert alone.describe().kernel == "native"
    me = alone.new_context(1, seed=5)
    crowd = [crowded.new_context(g % 3, seed=g) for g in range(20)]
    crowd[7] = crowded.new_context(1, seed=5)  # my twin, in the middle of the batch
    twin = exact.new_context(1, seed=5)
    rng = np.random.default_rng(2)
    worst = 0.0
    for _ in range(25):
        obs = rng.normal(size=(20, *ckpt.config.obs_shape)).astype(np.float32)
        xs = [crowded.prepare_observation(o) for o in obs]
        (a,) = alone.act([me], [xs[7]], True)
        batch = crowded.act(crowd, xs, True)
        np.testing.assert_array_equal(a, batch[7])
        (b,) = exact.act([twin], [exact.prepare_observation(obs[7])], True)
        worst = max(worst, float(np.abs(np.asarray(a) - np.asarray(b)).max()))
    assert 0.0 < worst < 0.05  # bf16 products, not fp32's, and still close to them


def test_precision_is_checked():
    ckpt = tiny_checkpoint(seed=3)
    with pytest.raises(ValueError, match="precision"):
        PolicyEngine(ckpt, precision="fp16")
    with pytest.raises(ValueError, match="native step"):
        PolicyEngine(ckpt, native=False, precision="bf16")


def test_bf16_on_a_build_without_it_is_refused_by_name(monkeypatch):
    monkeypatch.setattr(native, "has_bf16", lambda lib=None: False)
    with pytest.raises(ValueError, match="AVX-512 BF16"):
        PolicyEngine(tiny_checkpoint(seed=3, attention="window"), precision="bf16")
