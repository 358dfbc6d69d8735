"""Action sampling: the action modes, noise that is a pure function of (session seed, step), and the choice of
every row's action from the network's output at once.

Sampled actions need no stored random state: the noise of a session's step t depends only on its seed and t, so a
session continued by another replica (or rebuilt from a store) draws the very same noise.
"""

from __future__ import annotations

import math

import numpy as np

from gmt.model import native as native_kernel

# Discrete actions, default first: `expert` (paper A.1.3: sample among the logits above their 0.6 quantile).
ACTION_MODES = ("expert", "argmax", "sample")
CONTINUOUS_MODES = ("sample", "mean")  # continuous actions of a calibrated checkpoint, default first
MODES = ("argmax", "sample", "expert", "mean")  # index stored per slot
# Largest action-noise std (model space, actions in [-1, 1]) that `sample` adds. Trained behaviour levels explore
# with small noise (HalfCheetah: ~0.05) and sampling it reproduces their statistics; a uniform-random level's
# spread (~0.55) is the behaviour itself, and reproducing it tipped HalfCheetah into poses that no running data
# recovers from (6 of 15 switches out of the random goal failed uncapped; 0 of 15 capped at 0.1).
SAMPLE_STD_CAP = 0.1
EXPERT_QUANTILE = 0.6
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 arrays (wrapping arithmetic)."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def uniforms(seed: np.ndarray, step: np.ndarray, n: int, stream: int = 0) -> np.ndarray:
    """[B, n] uniforms in (0, 1), a pure function of (seed, step, stream): sampling needs no stored RNG state.

    Computed by the native library when it is available (one call instead of ~20 array operations; the same
    bits), else here.
    """
    out = native_kernel.uniforms(seed, step, n, stream)
    if out is not None:
        return out
    return numpy_uniforms(seed, step, n, stream)


def numpy_uniforms(seed: np.ndarray, step: np.ndarray, n: int, stream: int = 0) -> np.ndarray:
    """`uniforms` in numpy."""
    with np.errstate(over="ignore"):
        key = _mix(
            seed.astype(np.uint64) * _GOLDEN + _mix(step.astype(np.uint64) + np.uint64(stream) * _GOLDEN)
        )
        bits = _mix(key[:, None] + (np.arange(1, n + 1, dtype=np.uint64) * _GOLDEN)[None, :])
    return ((bits >> np.uint64(11)).astype(np.float64) + 0.5) / 2.0**53


def normals(seed: np.ndarray, step: np.ndarray, n: int) -> np.ndarray:
    """[B, n] standard normals from (seed, step) by Box-Muller (native when available, as `uniforms`)."""
    out = native_kernel.normals(seed, step, n)
    if out is not None:
        return out
    return numpy_normals(seed, step, n)


def numpy_normals(seed: np.ndarray, step: np.ndarray, n: int) -> np.ndarray:
    """`normals` in numpy."""
    u1, u2 = numpy_uniforms(seed, step, n, 1), numpy_uniforms(seed, step, n, 2)
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * math.pi * u2)


def noise_variance(action_noise: np.ndarray | None) -> np.ndarray | None:
    """[n_goals, A] variance of the noise `sample` adds: a checkpoint's per-goal action noise std capped at
    `SAMPLE_STD_CAP` (read when called), squared; None for an uncalibrated model."""
    if action_noise is None:
        return None
    return np.minimum(action_noise, SAMPLE_STD_CAP).astype(np.float64) ** 2


def choose(
    pred: np.ndarray,
    mode: np.ndarray,
    seed: np.ndarray,
    t: np.ndarray,
    g: np.ndarray,
    goal: np.ndarray,
    w: np.ndarray,
    noise_var: np.ndarray | None,
    discrete: bool,
) -> np.ndarray:
    """The action of every row at once, in model space.

    Args:
        pred: [B, A] predicted mean actions, or [B, n] logits of a discrete model.
        mode: [B] index into `MODES` of each row's action mode.
        seed: [B] session seeds; t: [B] the steps acted at (together they pick the noise).
        g: [B] goal token of the step (the goal faded out during a blend); goal: [B] the goal faded in.
        w: [B] weight of `goal` in the token (0 outside a blend): the noise's variance is blended alike.
        noise_var: [n_goals, A] variance `sample` adds (`noise_variance`), None when no row samples.
        discrete: Whether `pred` holds logits.

    Returns:
        [B] action ids (discrete), else [B, A] float32 actions clipped to [-1, 1].
    """
    if discrete:
        z = pred.astype(np.float64)  # [B, n] logits
        ids = z.argmax(axis=1)
        stoch = mode != MODES.index("argmax")
        if stoch.any():
            expert = (mode == MODES.index("expert"))[:, None]
            thr = np.quantile(z, EXPERT_QUANTILE, axis=1, keepdims=True)
            z = np.where(expert & (z < thr), -math.inf, z)
            prob = np.exp(z - z.max(axis=1, keepdims=True))
            cdf = np.cumsum(prob / prob.sum(axis=1, keepdims=True), axis=1)
            u = uniforms(seed, t, 1)  # [B, 1]
            drawn = np.minimum((cdf < u).sum(axis=1), z.shape[1] - 1)
            ids = np.where(stoch, drawn, ids)
        return ids
    a = pred
    sample = mode == MODES.index("sample")
    if sample.any():
        var = (1.0 - w[:, None]) * noise_var[g] + w[:, None] * noise_var[goal]  # [B, A]
        noise = np.sqrt(var) * normals(seed, t, a.shape[1])
        a = np.where(sample[:, None], a + noise, a)
    return np.clip(a, -1.0, 1.0).astype(np.float32)  # [B, A]
