"""A session's context: the engine-side handle and the stored form any replica can adopt.

`Context` is a handle on one slot of an engine's session pool, where the rolling history, the goal state and
(for `window` models) the key/value cache live as arrays, so that one act over many sessions is a few array
operations. `StoredContext` is the same context as plain values and arrays; it owns its byte encoding, which
walks the dataclass fields, so a field added here can never be silently dropped by a session store.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from gmt.model.pool import SessionPool

STORED_FORMAT_VERSION = 2
ARRAY_KINDS = "biuf"


class StoredContextError(ValueError):
    """Bytes or fields do not describe a stored context."""


@dataclass
class StoredContext:
    """A context as plain data. Arrays hold the last `n` steps before `step`, oldest first.

    Attributes:
        goal: The goal the session pursues (the target of a running blend).
        step: Timestep of the next observation.
        blend_from: Goal being faded out during a gradual switch (equal to `goal` otherwise).
        blend_steps: Length of the current gradual switch (0 = none).
        blend_done: Steps of the gradual switch already taken.
        action_mode: argmax / sample / expert (discrete) or sample / mean (continuous).
        seed: Seed of sampled actions (the noise of step t is a function of seed and t).
        version: Number of changes (acts, goal changes, resets) the context has seen.
        goals: [n] goal token of each step (the faded-out goal during a blend).
        blend_to: [n] second goal of each step's token.
        blend_w: [n] weight of `blend_to` in each step's token.
        states: [n, *obs_shape] normalised states.
        actions: [n, A] model-space actions taken ([n] ids for discrete actions).
    """

    goal: int
    step: int = 0
    blend_from: int = 0
    blend_steps: int = 0
    blend_done: int = 0
    action_mode: str = ""
    seed: int = 0
    version: int = 0
    goals: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    blend_to: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    blend_w: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    states: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    actions: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))

    @property
    def size(self) -> int:
        """Steps of history held."""
        return len(self.goals)

    @property
    def blend_remaining(self) -> int:
        """Steps left in the current gradual switch."""
        return max(self.blend_steps - self.blend_done, 0)

    def to_fields(self, prefix: str = "") -> dict[str, bytes]:
        """`<prefix>ctx` (JSON of the scalars and array layouts) and one `<prefix>arr:<name>` per array."""
        scalars, arrays, out = {}, {}, {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                a = np.ascontiguousarray(v)
                le = a.dtype.newbyteorder("<")
                arrays[f.name] = {"dtype": le.str, "shape": list(a.shape)}
                out[f"{prefix}arr:{f.name}"] = a.astype(le, copy=False).tobytes()
            else:
                scalars[f.name] = v
        meta = {"v": STORED_FORMAT_VERSION, "scalars": scalars, "arrays": arrays}
        out[f"{prefix}ctx"] = json.dumps(meta, separators=(",", ":")).encode()
        return out

    @classmethod
    def from_fields(cls, fields: dict[str, bytes], prefix: str = "") -> StoredContext:
        """Inverse of `to_fields`.

        Raises:
            StoredContextError: missing, unknown or malformed fields.
        """
        try:
            meta = json.loads(fields[f"{prefix}ctx"])
            if meta.get("v") != STORED_FORMAT_VERSION:
                raise StoredContextError(f"stored context v{meta.get('v')} is not v{STORED_FORMAT_VERSION}")
            known = {f.name for f in dataclasses.fields(cls)}
            names = set(meta["scalars"]) | set(meta["arrays"])
            if names != known:
                raise StoredContextError(f"stored context fields {sorted(names ^ known)} do not match")
            arrays = {k: _array(d, fields.get(f"{prefix}arr:{k}"), k) for k, d in meta["arrays"].items()}
            return cls(**meta["scalars"], **arrays)
        except StoredContextError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise StoredContextError(f"unreadable stored context: {type(e).__name__}: {e}") from e


def _array(desc: dict, raw: bytes | None, name: str) -> np.ndarray:
    dt = np.dtype(desc["dtype"])
    if dt.kind not in ARRAY_KINDS or raw is None:
        raise StoredContextError(f"array {name}: bad dtype {dt} or missing bytes")
    shape = tuple(int(s) for s in desc["shape"])
    if int(np.prod(shape)) * dt.itemsize != len(raw):
        raise StoredContextError(f"array {name}: {len(raw)} bytes do not fill shape {shape} of {dt}")
    return np.frombuffer(raw, dtype=dt).reshape(shape).astype(dt.newbyteorder("="))


class Context:
    """A handle on one session's slot in an engine's pool; reads are live views of the pool.

    Attributes:
        pool: The pool holding the session's arrays.
        slot: The session's slot.
        key: The session id the slot is registered under (None for anonymous contexts).
    """

    __slots__ = ("pool", "slot", "key")

    def __init__(self, pool: SessionPool, slot: int, key: str | None = None) -> None:
        self.pool, self.slot, self.key = pool, slot, key

    def _get(self, name: str) -> int:
        return int(getattr(self.pool, name)[self.slot])

    goal = property(lambda self: self._get("goal"), doc="The goal the session pursues.")
    step = property(lambda self: self._get("step"), doc="Timestep of the next observation.")
    blend_from = property(lambda self: self._get("blend_from"), doc="Goal being faded out.")
    blend_steps = property(lambda self: self._get("blend_steps"), doc="Length of the running blend.")
    blend_done = property(lambda self: self._get("blend_done"), doc="Steps of the blend already taken.")
    seed = property(lambda self: self._get("seed"), doc="Seed of sampled actions.")
    version = property(lambda self: self._get("version"), doc="Number of changes seen.")

    @property
    def action_mode(self) -> str:
        """The session's action mode."""
        return self.pool.modes[self._get("mode")]

    @property
    def blend_remaining(self) -> int:
        """Steps left in the current gradual switch."""
        return max(self.blend_steps - self.blend_done, 0)

    @property
    def size(self) -> int:
        """Steps of history held (at most the model's `history_steps`)."""
        return min(self.step, self.pool.H)

    def _hist(self, name: str) -> np.ndarray:
        t, n, H = self.step, self.size, self.pool.H
        pos = np.arange(t - n, t) % H
        return getattr(self.pool, name)[self.slot, pos].copy()

    goals = property(lambda self: self._hist("h_goal"), doc="[n] goal tokens, oldest first.")
    blend_to = property(lambda self: self._hist("h_blend_to"), doc="[n] second goal of each token.")
    blend_w = property(lambda self: self._hist("h_blend_w"), doc="[n] weight of `blend_to`.")
    states = property(lambda self: self._hist("h_state"), doc="[n, *obs_shape] normalised states.")
    actions = property(lambda self: self._hist("h_action"), doc="[n, A] model-space actions taken.")

    @property
    def timesteps(self) -> np.ndarray:
        """[n] timesteps of the steps held."""
        return np.arange(self.step - self.size, self.step)

    def scalars(self) -> dict:
        """The stored form's scalar fields (goal, step, blend, mode, seed, version) as plain values, in one read
        (`scalars_of`: the same for many contexts at once)."""
        p, i = self.pool, self.slot
        return {
            "goal": int(p.goal[i]),
            "step": int(p.step[i]),
            "blend_from": int(p.blend_from[i]),
            "blend_steps": int(p.blend_steps[i]),
            "blend_done": int(p.blend_done[i]),
            "action_mode": p.modes[p.mode[i]],
            "seed": int(p.seed[i]),
            "version": int(p.version[i]),
        }

    @staticmethod
    def scalars_of(pool, slots: np.ndarray) -> list[dict]:
        """`scalars` of the contexts at `slots` [n] of `pool`, each column read once for all of them."""
        cols = [getattr(pool, n)[slots].tolist() for n in ("goal", "step", "blend_from", "blend_steps")]
        cols += [getattr(pool, n)[slots].tolist() for n in ("blend_done", "mode", "seed", "version")]
        return [
            {
                "goal": goal,
                "step": step,
                "blend_from": blend_from,
                "blend_steps": blend_steps,
                "blend_done": blend_done,
                "action_mode": pool.modes[mode],
                "seed": seed,
                "version": version,
            }
            for goal, step, blend_from, blend_steps, blend_done, mode, seed, version in zip(
                *cols, strict=True
            )
        ]

    def layout(self) -> dict:
        """How a held step is shaped: `H` (steps held at most), `state` and `action` as [dtype, shape]."""
        p = self.pool
        return {
            "H": int(p.H),
            "state": [p.h_state.dtype.str, list(p.h_state.shape[2:])],
            "action": [p.h_action.dtype.str, list(p.h_action.shape[2:])],
        }

    def held(self, t: int) -> tuple[int, int, float, np.ndarray, np.ndarray]:
        """Held step `t` (one of the last `size` steps): goal token, blend target, blend weight, state, action."""
        p, s, pos = self.pool, self.slot, t % self.pool.H
        return (
            int(p.h_goal[s, pos]),
            int(p.h_blend_to[s, pos]),
            float(p.h_blend_w[s, pos]),
            p.h_state[s, pos],
            p.h_action[s, pos],
        )

    def to_stored(self) -> StoredContext:
        """The context as plain data (what a session store persists)."""
        return StoredContext(
            goal=self.goal,
            step=self.step,
            blend_from=self.blend_from,
            blend_steps=self.blend_steps,
            blend_done=self.blend_done,
            action_mode=self.action_mode,
            seed=self.seed,
            version=self.version,
            goals=self.goals,
            blend_to=self.blend_to,
            blend_w=self.blend_w,
            states=self.states,
            actions=self.actions,
        )
