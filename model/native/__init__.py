"""The native incremental step: `gmt_step.c`, compiled on first use with the system C compiler, called by ctypes.

The torch step (`GMT.step`) is the reference; this one does the same arithmetic in one C call, which matters for
one session's latency (see `gmt_step.c`). Without a C compiler, or with `GMT_NATIVE=0`, `load()` returns None
and the engine keeps the torch step.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import platform
import subprocess
import tempfile
from concurrent import futures
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from gmt.model.gmt import GMT

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("gmt_step.c")
TILE = 32  # NB in gmt_step.c: output columns per packed weight tile
ROWS_PER_THREAD = 32  # `act(threads=n)` splits a pass only where each thread gets at least this many rows
CFLAGS = [
    "-O3",
    "-march=native",
    *(["-mprefer-vector-width=512"] if platform.machine() in ("x86_64", "AMD64") else []),  # an x86-only flag
    "-fPIC",
    "-shared",
    "-std=c11",
    "-ffp-contract=fast",
]

_f32p = ctypes.POINTER(ctypes.c_float)
_f32pp = ctypes.POINTER(_f32p)
_u32pp = ctypes.POINTER(ctypes.POINTER(ctypes.c_uint32))
_i64p = ctypes.POINTER(ctypes.c_int64)


_INTS = ("n_embd", "n_head", "n_layer", "obs_dim", "act_dim", "discrete", "n_goals", "max_timestep")
_INTS += ("context_length",)
_TABLES = ("goal_emb", "state_w", "state_b", "action_w", "action_b", "time_emb", "ln_in_w", "ln_in_b")
_LAYERS = ("ln1_w", "ln1_b", "qkv_w", "qkv_b", "proj_w", "proj_b", "ln2_w", "ln2_b", "fc_w", "fc_b")
_LAYERS += ("out_w", "out_b")
_HEADS = ("ln_f_w", "ln_f_b", "head_w", "head_b")
_BF16 = ("qkv_wb", "proj_wb", "fc_wb", "out_wb")  # the blocks' matrices in bfloat16 (NULL: fp32)


class _Pool(ctypes.Structure):
    """Mirror of `Pool` in gmt_step.c: the addresses of a `SessionPool`'s arrays."""

    _fields_ = [(n, ctypes.c_int64) for n in ("n_slots", "H", "sample_mode")] + [
        (n, ctypes.c_void_p)
        for n in (
            "step", "goal", "blend_from", "blend_steps", "blend_done", "mode", "version", "seed",
            "h_goal", "h_blend_to", "h_blend_w", "h_state", "h_action", "noise_var", "kc", "vc", "tok",
        )
    ] + [("W", ctypes.c_int64)]  # fmt: skip


class _Model(ctypes.Structure):
    """Mirror of `Model` in gmt_step.c (same field order)."""

    _fields_ = (
        [(n, ctypes.c_int64) for n in _INTS]
        + [(n, _f32p) for n in _TABLES]
        + [(n, _f32pp) for n in _LAYERS]
        + [(n, _f32p) for n in _HEADS]
        + [(n, _u32pp) for n in _BF16]
    )


def _cache_dir() -> Path:
    root = os.environ.get("GMT_NATIVE_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "gmt-native"
    )
    return Path(root)


def _cpu_features() -> str:
    """The CPU's instruction-set features as the kernel reports them ('' where /proc/cpuinfo has none)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor()
    for line in text.splitlines():
        name, _, value = line.partition(":")
        if name.strip() in ("flags", "Features"):  # x86, Arm
            return " ".join(sorted(value.split()))
    return ""


def library_key(cc: str) -> str:
    """Cache key of the compiled library: source, compiler, flags, and the host and CPU it is built for.

    `-march=native` makes the library specific to the CPU's features: a cache shared by machines with other
    features (a home directory on NFS, a copied container layer) must not hand one CPU another's build (SIGILL).
    """
    parts = [cc, *CFLAGS, platform.machine(), platform.node(), _cpu_features()]
    return hashlib.sha256(SOURCE.read_bytes() + " ".join(parts).encode()).hexdigest()[:16]


_lib: ctypes.CDLL | None = None
_tried = False


def load() -> ctypes.CDLL | None:
    """The compiled library (built once per `library_key`, cached on disk), or None if unavailable."""
    global _lib, _tried
    if _tried:
        return _lib
    _tried = True
    if os.environ.get("GMT_NATIVE", "1") == "0":
        log.info("native step disabled by GMT_NATIVE=0")
        return None
    cc = os.environ.get("CC", "cc")
    so = _cache_dir() / f"gmt_step-{library_key(cc)}.so"
    try:
        if not so.exists():
            so.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=so.parent) as tmp:
                built = Path(tmp) / so.name
                subprocess.run(
                    [cc, *CFLAGS, str(SOURCE), "-o", str(built), "-lm"],
                    check=True,
                    capture_output=True,
                    text=True,
                )
                os.replace(built, so)  # atomic: concurrent builders never see a partial file
        lib = ctypes.CDLL(str(so))
    except (OSError, subprocess.CalledProcessError) as e:
        detail = e.stderr if isinstance(e, subprocess.CalledProcessError) else e
        log.warning("native step unavailable, using the torch step: %s", detail)
        return None
    lib.gmt_step.restype = ctypes.c_int
    # Pointers pass as plain addresses (`ndarray.ctypes.data`): a third of the cost of typed pointers per call.
    vp, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.gmt_step.argtypes = [ctypes.POINTER(_Model), i64, *[vp] * 12, i64, i64, vp]
    lib.gmt_act.restype = ctypes.c_int
    lib.gmt_act.argtypes = [ctypes.POINTER(_Model), ctypes.POINTER(_Pool), i64, vp, vp, vp, vp]
    lib.gmt_bf16.restype = ctypes.c_int
    lib.gmt_bf16.argtypes = []
    lib.gmt_linear.restype = ctypes.c_int
    lib.gmt_linear.argtypes = [vp, i64, i64, vp, vp, i64, vp, ctypes.c_int]
    lib.gmt_uniforms.restype = lib.gmt_normals.restype = None
    lib.gmt_uniforms.argtypes = [vp, vp, i64, i64, i64, vp]
    lib.gmt_normals.argtypes = [vp, vp, i64, i64, vp]
    _lib = lib
    return lib


def linear(x: np.ndarray, w: np.ndarray, b: np.ndarray | None = None, bf16: bool = False) -> np.ndarray:
    """x [M, K] @ w [K, N] + b as the native step computes one of a block's products (fp32, or bf16 products with
    `bf16`): for tests. Raises where the library or its bf16 build is missing."""
    lib = load()
    if lib is None or (bf16 and not has_bf16(lib)):
        raise RuntimeError("the native library (with bf16 products, if asked) is not available")
    x = np.ascontiguousarray(x, np.float32)
    packed = pack_bf16(w) if bf16 else pack(np.asarray(w, np.float32))
    b = None if b is None else np.ascontiguousarray(b, np.float32)
    y = np.empty((x.shape[0], w.shape[1]), np.float32)
    rc = lib.gmt_linear(x.ctypes.data, x.shape[0], x.shape[1], packed.ctypes.data, _addr(b), w.shape[1],
                        y.ctypes.data, int(bf16))  # fmt: skip
    if rc != 0:
        raise MemoryError("the native product could not allocate its scratch memory")
    return y


def serves(cfg) -> bool:
    """Whether the native step computes this model's incremental step (a `GMTConfig`): window attention over
    vector observations."""
    return cfg.attention == "window" and not cfg.is_image


def has_bf16(lib: ctypes.CDLL | None = None) -> bool:
    """Whether the native library (`load()` by default) was built with bfloat16 products (AVX-512 BF16)."""
    lib = load() if lib is None else lib
    return lib is not None and bool(lib.gmt_bf16())


def uniforms(seed: np.ndarray, step: np.ndarray, n: int, stream: int = 0) -> np.ndarray | None:
    """`gmt.model.sampling.uniforms` computed natively ([B, n] float64), or None without the library."""
    lib = load()
    if lib is None:
        return None
    seed, step = np.ascontiguousarray(seed, np.uint64), np.ascontiguousarray(step, np.int64)
    out = np.empty((len(seed), n))
    lib.gmt_uniforms(seed.ctypes.data, step.ctypes.data, len(seed), n, stream, out.ctypes.data)
    return out


def normals(seed: np.ndarray, step: np.ndarray, n: int) -> np.ndarray | None:
    """`gmt.model.sampling.normals` computed natively ([B, n] float64), or None without the library."""
    lib = load()
    if lib is None:
        return None
    seed, step = np.ascontiguousarray(seed, np.uint64), np.ascontiguousarray(step, np.int64)
    out = np.empty((len(seed), n))
    lib.gmt_normals(seed.ctypes.data, step.ctypes.data, len(seed), n, out.ctypes.data)
    return out


def _ptr(a: np.ndarray | None, kind=_f32p):
    return None if a is None else a.ctypes.data_as(kind)


def pack(w: np.ndarray) -> np.ndarray:
    """A matrix [K, N] as ceil(N / TILE) contiguous column tiles [K, TILE], zero-padded: the layout `linear`
    in gmt_step.c streams."""
    K, N = w.shape
    n_tiles = -(-N // TILE)
    padded = np.zeros((K, n_tiles * TILE), np.float32)
    padded[:, :N] = w
    return np.ascontiguousarray(padded.reshape(K, n_tiles, TILE).transpose(1, 0, 2))  # [tiles, K, TILE]


def bf16_bits(a: np.ndarray) -> np.ndarray:
    """float32 values as bfloat16 bit patterns (uint32, low 16 bits), rounded to nearest even, denormals flushed to
    zero: what `vcvtne2ps2bf16` makes of them (`bf16_of` in gmt_step.c)."""
    u = np.ascontiguousarray(a, np.float32).view(np.uint32)
    out = ((u + np.uint32(0x7FFF) + ((u >> 16) & 1)) >> 16) & 0xFFFF
    out = np.where((u & 0x7F800000) == 0, (u >> 16) & 0x8000, out)  # zero or denormal: signed zero
    return np.where((u & 0x7FFFFFFF) > 0x7F800000, ((u >> 16) | 0x40) & 0xFFFF, out).astype(np.uint32)


def pack_bf16(w: np.ndarray) -> np.ndarray:
    """A matrix [K, N] (K even) as ceil(N / TILE) column tiles [K / 2, TILE] of bfloat16 pairs (rows k and k + 1 of
    a column in one uint32, k in the low half), zero-padded: the layout `linear_bf16` in gmt_step.c streams."""
    K, N = w.shape
    if K % 2:
        raise ValueError(f"bfloat16 products need an even inner dimension, got {K}")
    bits = bf16_bits(pack(w))  # [tiles, K, TILE]
    return np.ascontiguousarray(bits[:, 0::2, :] | (bits[:, 1::2, :] << 16))  # [tiles, K / 2, TILE]


def _addr(a: np.ndarray | None) -> int | None:
    return None if a is None else a.ctypes.data


class NativeStep:
    """`GMT.step` of one vector-observation `window` model, computed by `gmt_step.c`.

    Args:
        model: The model (its weights are copied, transposed, once).
        lib: The library from `load()`.
        bf16: Compute the blocks' four matrix products in bfloat16 (weights and activations rounded to bfloat16,
            fp32 sums: `vdpbf16ps`); the rest stays fp32. Needs a build with AVX-512 BF16 (`has_bf16`).
    """

    def __init__(self, model: GMT, lib: ctypes.CDLL, bf16: bool = False) -> None:
        cfg = model.cfg
        if bf16 and not has_bf16(lib):
            raise ValueError(
                "bfloat16 products need a CPU with AVX-512 BF16 (and a compiler that targets it); this one has none"
            )
        self.bf16 = bf16
        if not serves(cfg):
            raise ValueError("the native step serves window models with vector observations")
        self.cfg, self._lib = cfg, lib
        self._keep: list = []  # every array the struct points into

        def arr(t: torch.Tensor, transpose: bool = False) -> np.ndarray:
            """A table as is; a Linear's weight [out, in] transposed and packed (`pack`)."""
            a = t.detach().float().cpu().numpy()
            a = pack(a.T) if transpose else np.ascontiguousarray(a, dtype=np.float32)
            self._keep.append(a)
            return a

        def per_layer(get, transpose: bool = False):
            ptrs = (_f32p * cfg.n_layer)(*(_ptr(arr(get(b), transpose)) for b in model.blocks))
            self._keep.append(ptrs)
            return ctypes.cast(ptrs, _f32pp)

        m = _Model()
        m.n_embd, m.n_head, m.n_layer = cfg.n_embd, cfg.n_head, cfg.n_layer
        m.obs_dim, m.act_dim, m.discrete = cfg.obs_shape[0], cfg.act_dim, int(cfg.discrete_actions)
        m.n_goals, m.max_timestep, m.context_length = cfg.n_goals, cfg.max_timestep, cfg.context_length
        m.goal_emb, m.time_emb = _ptr(arr(model.goal_emb.weight)), _ptr(arr(model.time_emb.weight))
        m.state_w, m.state_b = _ptr(arr(model.state_emb.weight, True)), _ptr(arr(model.state_emb.bias))
        if cfg.discrete_actions:  # the embedding table [act_dim, C]
            m.action_w, m.action_b = _ptr(arr(model.action_emb.weight)), None
        else:
            m.action_w, m.action_b = (
                _ptr(arr(model.action_emb.weight, True)),
                _ptr(arr(model.action_emb.bias)),
            )
        m.ln_in_w, m.ln_in_b = _ptr(arr(model.ln_in.weight)), _ptr(arr(model.ln_in.bias))
        m.ln1_w, m.ln1_b = per_layer(lambda b: b.ln1.weight), per_layer(lambda b: b.ln1.bias)
        m.qkv_w, m.qkv_b = per_layer(lambda b: b.attn.qkv.weight, True), per_layer(lambda b: b.attn.qkv.bias)
        m.proj_w = per_layer(lambda b: b.attn.proj.weight, True)
        m.proj_b = per_layer(lambda b: b.attn.proj.bias)
        m.ln2_w, m.ln2_b = per_layer(lambda b: b.ln2.weight), per_layer(lambda b: b.ln2.bias)
        m.fc_w, m.fc_b = per_layer(lambda b: b.fc.weight, True), per_layer(lambda b: b.fc.bias)
        m.out_w, m.out_b = per_layer(lambda b: b.out.weight, True), per_layer(lambda b: b.out.bias)
        m.ln_f_w, m.ln_f_b = _ptr(arr(model.ln_f.weight)), _ptr(arr(model.ln_f.bias))
        m.head_w, m.head_b = _ptr(arr(model.action_head.weight, True)), _ptr(arr(model.action_head.bias))
        if bf16:
            for name, get in (
                ("qkv_wb", lambda b: b.attn.qkv.weight),
                ("proj_wb", lambda b: b.attn.proj.weight),
                ("fc_wb", lambda b: b.fc.weight),
                ("out_wb", lambda b: b.out.weight),
            ):
                tiles = [pack_bf16(get(b).detach().float().cpu().numpy().T) for b in model.blocks]
                ptrs = (ctypes.POINTER(ctypes.c_uint32) * cfg.n_layer)(
                    *(t.ctypes.data_as(ctypes.POINTER(ctypes.c_uint32)) for t in tiles)
                )
                self._keep += [*tiles, ptrs]
                setattr(m, name, ctypes.cast(ptrs, _u32pp))
        self._model = m
        self._model_ref = ctypes.byref(m)

    def __call__(
        self,
        prev_actions: np.ndarray,
        goals: np.ndarray,
        states: np.ndarray,
        timesteps: np.ndarray,
        cache,
        slots: np.ndarray,
        blend_to: np.ndarray | None = None,
        blend_w: np.ndarray | None = None,
    ) -> np.ndarray:
        """As `GMT.step`, on numpy arrays: [B, act_dim] float32 predictions."""
        B = len(slots)
        i64 = lambda a: np.ascontiguousarray(a, dtype=np.int64)  # noqa: E731
        f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
        goals, timesteps, slots, states = i64(goals), i64(timesteps), i64(slots), f32(states)
        if self.cfg.discrete_actions:
            prev_f, prev_i = None, i64(prev_actions)
        else:
            prev_f, prev_i = f32(prev_actions), None
        if blend_to is not None:
            blend_to, blend_w = i64(blend_to), f32(blend_w)
        for t in (cache.k, cache.v, cache.tok):
            if not t.is_contiguous():
                raise ValueError("the key/value cache must be contiguous")
        out = np.empty((B, self.cfg.act_dim), dtype=np.float32)
        rc = self._lib.gmt_step(
            self._model_ref,
            B,
            _addr(prev_f),
            _addr(prev_i),
            goals.ctypes.data,
            _addr(blend_to),
            _addr(blend_w),
            states.ctypes.data,
            None,
            timesteps.ctypes.data,
            slots.ctypes.data,
            cache.k.data_ptr(),
            cache.v.data_ptr(),
            cache.tok.data_ptr(),
            cache.n_slots,
            cache.width,
            out.ctypes.data,
        )
        if rc != 0:
            raise MemoryError("the native step could not allocate its scratch memory")
        return out

    def act(
        self,
        pool,
        slots: np.ndarray,
        states: np.ndarray,
        noise_var: np.ndarray | None,
        sample_mode: int,
        threads: int = 1,
    ):
        """`PolicyEngine._step` for continuous actions, in one native call: the step, the noise of `sample`
        rows, clipping and the commit of the rows that succeeded to `pool` (a `gmt.model.pool.SessionPool`).

        With `threads` > 1 the rows are split into that many contiguous parts (each of at least
        `ROWS_PER_THREAD` rows, else fewer parts), one native call each, run at once: the step is batch invariant
        and the parts' slots are distinct, so the answers and the pool are the same bit for bit. (A part that
        cannot allocate its scratch memory changes nothing, but the others' rows are then committed.)

        Returns:
            (model-space actions [B, A] float32, ok [B] bool).
        """
        if self.cfg.discrete_actions:
            raise ValueError("the native act serves continuous actions")
        if getattr(self, "_pool_key", None) != (id(pool), pool.generation):
            self._pool = self._pool_struct(pool, noise_var, sample_mode)
            self._pool_key = (id(pool), pool.generation)
        B = len(slots)
        slots = np.ascontiguousarray(slots, dtype=np.int64)
        states = np.ascontiguousarray(states, dtype=np.float32)
        taken = np.empty((B, self.cfg.act_dim), dtype=np.float32)
        ok = np.empty(B, dtype=np.bool_)

        def call(lo: int, hi: int) -> tuple:  # gmt_act's arguments for rows lo:hi
            return (
                self._model_ref,
                self._pool_ref,
                hi - lo,
                slots.ctypes.data + slots.itemsize * lo,
                states.ctypes.data + states.strides[0] * lo,
                taken.ctypes.data + taken.strides[0] * lo,
                ok.ctypes.data + ok.itemsize * lo,
            )

        parts = min(threads, B // ROWS_PER_THREAD)
        if parts <= 1:
            failed = self._lib.gmt_act(*call(0, B)) != 0
        else:
            bounds = [B * i // parts for i in range(parts + 1)]
            failed = self._run_parts([call(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)])
        if failed:
            raise MemoryError("the native step could not allocate its scratch memory")
        return taken, ok

    def _run_parts(self, calls: list[tuple]) -> bool:
        """Run `gmt_act` once per argument tuple, the first here and the others on helper threads, all at once
        (ctypes lets go of the GIL); whether any failed. Returns only once every part has."""
        others = []
        try:
            for c in calls[1:]:
                others.append(_helpers(len(calls) - 1).submit(self._lib.gmt_act, *c))
            rc = self._lib.gmt_act(*calls[0])
        finally:  # no part may outlive the arrays it writes
            futures.wait(others)
        return rc != 0 or any(f.result() != 0 for f in others)

    def _pool_struct(self, pool, noise_var: np.ndarray | None, sample_mode: int) -> _Pool:
        """The pool's array addresses (valid until its arrays are replaced: `pool.generation` changes)."""
        for name in ("step", "goal", "blend_from", "blend_steps", "blend_done", "mode", "version", "seed"):
            a = getattr(pool, name)
            if not a.flags.c_contiguous or a.dtype.itemsize != 8:
                raise ValueError(f"pool array {name} must be contiguous 64-bit")
        cache = pool.cache
        for t in (cache.k, cache.v, cache.tok):
            if not t.is_contiguous():
                raise ValueError("the key/value cache must be contiguous")
        self._noise_var = None if noise_var is None else np.ascontiguousarray(noise_var, dtype=np.float64)
        st = _Pool()
        st.n_slots, st.H, st.sample_mode = pool.n_slots, pool.H, sample_mode
        for name in ("step", "goal", "blend_from", "blend_steps", "blend_done", "mode", "version", "seed"):
            setattr(st, name, getattr(pool, name).ctypes.data)
        for name, dtype in (("h_goal", np.int64), ("h_blend_to", np.int64), ("h_blend_w", np.float32)):
            a = getattr(pool, name)
            assert a.dtype == dtype and a.flags.c_contiguous
            setattr(st, name, a.ctypes.data)
        for name in ("h_state", "h_action"):
            a = getattr(pool, name)
            assert a.dtype == np.float32 and a.flags.c_contiguous
            setattr(st, name, a.ctypes.data)
        st.noise_var = None if self._noise_var is None else self._noise_var.ctypes.data
        st.kc, st.vc, st.tok, st.W = cache.k.data_ptr(), cache.v.data_ptr(), cache.tok.data_ptr(), cache.width
        self._pool_ref = ctypes.byref(st)
        return st


@functools.cache
def _helpers(n: int) -> ThreadPoolExecutor:
    """The threads that run all but the first part of a split native step (`NativeStep.act(threads=n + 1)`)."""
    return ThreadPoolExecutor(n, thread_name_prefix="gmt-step")
