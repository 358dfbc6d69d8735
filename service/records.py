"""Sessions as records: every session's goal timeline, and the episode a recorded session keeps.

Each session carries a `Ledger`:
- **the timeline**: every goal the session had, one JSON entry per change `{"step", "episode", "goal", "given",
  "blend_steps", "by", "at"}` (`by`: create, reset, rest, grpc or stream), appended by creation, each goal change
  and each reset. A goal change repeating the last entry (same episode, step, goal, given and blend) is a retry:
  it changes nothing and adds nothing;
- **the recording** (sessions created with `record`, or drawn by `--record-share`): one `StepRecord` per answered
  step (episode, step, goal token, goal, blend weight, time, the observation as the model received it, the action
  as answered, and the client's report on the previous step's action), at most `max_steps` of them; past that the
  recording stops (`stopped`) and the session goes on unrecorded.

A change (act, goal change, reset) puts its new entries in `Ledger.new_timeline` / `Ledger.new_records`; the
store writes them with the change itself (Redis: in the same script call, only when its compare-and-set passes,
so a retried or aborted act never adds a record twice) and then calls `Ledger.written`.

`assemble` turns a ledger's entries into a `gmt.common.recording.Recording` (the JSON and .npz answers of
`GET /sessions/{id}/recording`, and the files written at close and expiry).
"""

from __future__ import annotations

import hashlib
import math
import re
import struct
from dataclasses import dataclass, field

import numpy as np
import orjson

from gmt.common.recording import FORMAT, INFO_PREFIX, VERSION, Recording
from gmt.service.errors import InvalidArgument, ResourceExhausted

MAX_INFO_KEYS = 32  # keys of a reported info object
INFO_KEY = re.compile(r"[A-Za-z0-9_.:/-]{1,64}")  # an info key: letters, digits and _ . : / - (1 to 64)
MAX_REPORTED = 1e12  # largest |value| of a reported reward or info value
MAX_TIMELINE = 100_000  # timeline entries kept per session; later changes still apply, unlisted
MAX_GOALS_PER_STEP = 16  # goal changes taking effect at one step of a session (no act in between) at most
MAX_RECORD_STEPS = 10_000_000  # the largest --record-max-steps
BY = ("create", "reset", "rest", "grpc", "stream")

_HEAD = struct.Struct("<qqqqfd")  # episode, t, goal token, goal, blend weight, time


@dataclass(frozen=True)
class Report:
    """What a client reports, with an act, about the outcome of its previous action (all optional)."""

    reward: float | None = None
    terminated: bool | None = None
    truncated: bool | None = None
    info: dict[str, float] | None = None

    def to_json(self) -> bytes:
        """The report as compact JSON (only the fields given)."""
        d = {
            k: v
            for k, v in (("r", self.reward), ("te", self.terminated), ("tr", self.truncated))
            if v is not None
        }
        if self.info:
            d["i"] = self.info
        return orjson.dumps(d)


def check_report(
    reward: object = None, terminated: object = None, truncated: object = None, info: object = None
) -> Report | None:
    """The report an act carries, validated; None when it carries none. The one owner of these rules.

    Raises:
        InvalidArgument: a reward or info value that is not a finite number within +-1e12, a flag that is not a
            boolean, or an info that is not a flat object of at most 32 numbers named by `INFO_KEY`.
    """
    if reward is None and terminated is None and truncated is None and info is None:
        return None
    if reward is not None:
        reward = _number("reward", reward)
    for name, flag in (("terminated", terminated), ("truncated", truncated)):
        if flag is not None and not isinstance(flag, bool):
            raise InvalidArgument(f"{name} must be true or false, got {flag!r:.40}")
    if info is not None:
        if not isinstance(info, dict):
            raise InvalidArgument('info must be a flat object of numbers, e.g. {"x_velocity": 1.5}')
        if len(info) > MAX_INFO_KEYS:
            raise InvalidArgument(f"info has {len(info)} keys; at most {MAX_INFO_KEYS} are accepted")
        checked = {}
        for k, v in info.items():
            if not isinstance(k, str) or not INFO_KEY.fullmatch(k):
                shown = repr(k) if isinstance(k, str) and len(k) <= 64 else "given"
                raise InvalidArgument(
                    f"info key {shown} is not 1 to 64 letters, digits, '_', '.', ':', '/' or '-'"
                )
            checked[k] = _number(f"info[{k!r}]", v)
        info = checked
    return Report(reward, terminated, truncated, info or None)


def _number(name: str, v: object) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
        raise InvalidArgument(f"{name} must be a number, got {type(v).__name__}")
    x = float(v)
    if not math.isfinite(x) or abs(x) > MAX_REPORTED:
        raise InvalidArgument(f"{name} must be a finite number within +-1e12, got {x!r}")
    return x


@dataclass(frozen=True)
class Layout:
    """How one step's observation and action are stored: dtypes and shapes (from the model)."""

    obs_dtype: str
    obs_shape: tuple[int, ...]
    action_dtype: str
    action_shape: tuple[int, ...]

    @classmethod
    def of_model(cls, obs_shape: tuple[int, ...], image: bool, discrete: bool, act_dim: int) -> Layout:
        """Float32 observations (uint8 for images); float32 [A] actions, or one int64 for discrete ones."""
        return cls(
            "|u1" if image else "<f4",
            tuple(int(s) for s in obs_shape),
            "<i8" if discrete else "<f4",
            () if discrete else (int(act_dim),),
        )

    def to_dict(self) -> dict:
        """JSON-ready."""
        return {
            "obs": [self.obs_dtype, list(self.obs_shape)],
            "action": [self.action_dtype, list(self.action_shape)],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Layout:
        """Inverse of `to_dict`."""
        (od, os_), (ad, as_) = d["obs"], d["action"]
        return cls(od, tuple(os_), ad, tuple(as_))

    @property
    def obs_bytes(self) -> int:
        """Bytes of one stored observation."""
        return int(np.prod(self.obs_shape, dtype=np.int64)) * np.dtype(self.obs_dtype).itemsize

    @property
    def action_bytes(self) -> int:
        """Bytes of one stored action."""
        return int(np.prod(self.action_shape, dtype=np.int64)) * np.dtype(self.action_dtype).itemsize


@dataclass
class Ledger:
    """A session's timeline and recording state (see the module docstring).

    Attributes:
        episode: The session's episode (0, then +1 at each reset).
        last: The last timeline entry (decoded), None before creation is recorded.
        entries: Timeline entries written so far (the next one's index).
        layout: The step layout when the session records, else None.
        max_steps: Steps a recording keeps at most.
        recorded: Steps recorded so far.
        new_timeline: Timeline entries (JSON) the change in flight appends.
        new_records: Step records the change in flight appends.
        last_changed: The change in flight changed `last` (a shared store writes it with the change).
        timeline: Every entry, where the store keeps the ledger in this process (memory), else None.
        records: Every step record, likewise.
    """

    episode: int = 0
    last: dict | None = None
    entries: int = 0
    layout: Layout | None = None
    max_steps: int = 0
    recorded: int = 0
    new_timeline: list[bytes] = field(default_factory=list)
    new_records: list[bytes] = field(default_factory=list)
    last_changed: bool = False
    timeline: list[bytes] | None = None
    records: list[bytes] | None = None

    @property
    def recording(self) -> bool:
        """Whether the session records (even if its recording stopped)."""
        return self.layout is not None

    @property
    def stopped(self) -> str | None:
        """Why the recording stopped before the session ended, or None."""
        if self.layout is not None and self.recorded >= self.max_steps:
            return (
                f"the recording reached its maximum of {self.max_steps} steps (--record-max-steps); the session "
                "went on unrecorded"
            )
        return None

    @property
    def changed(self) -> bool:
        """Whether the change in flight appends anything."""
        return bool(self.new_timeline or self.new_records)

    def note_goal(self, step: int, goal: int, given: dict, blend_steps: int, by: str, now: float) -> bool:
        """Append a timeline entry for a goal taking effect at `step`; False when it repeats the last entry
        (a retried change: nothing is appended and nothing should change).

        Raises:
            ResourceExhausted: `MAX_GOALS_PER_STEP` changes already take effect at `step` (only the last of
                them is ever used: an act must come first), and nothing is appended.
        """
        entry = {
            "step": step,
            "episode": self.episode,
            "goal": goal,
            "given": given,
            "blend_steps": blend_steps,
        }
        last = self.last
        if (
            last is not None
            and by not in ("create", "reset")
            and all(last.get(k) == v for k, v in entry.items())
        ):
            return False
        same_step = last is not None and (last.get("episode"), last.get("step")) == (self.episode, step)
        if by in ("create", "reset"):
            k = 0  # a change of its own counts from here
        else:
            k = last.get("k", 1) + 1 if same_step else 1
        if k > MAX_GOALS_PER_STEP:
            raise ResourceExhausted(
                f"the session's goal changed {MAX_GOALS_PER_STEP} times at step {step} with no act in between "
                "(only the last is used): act before changing it again"
            )
        entry |= {"by": by, "at": now, "n": self.entries, "k": k}
        self.last, self.last_changed = entry, True
        if self.entries < MAX_TIMELINE:
            self.new_timeline.append(orjson.dumps(entry))
        self.entries += 1
        return True

    def note_step(
        self,
        t: int,
        goal_token: int,
        goal: int,
        blend_w: float,
        now: float,
        observation: np.ndarray,
        action,
        report: Report | None,
    ) -> bool:
        """Append the record of answered step `t` when the session records and its recording has room."""
        lay = self.layout
        if lay is None or self.recorded >= self.max_steps:
            return False
        obs = np.ascontiguousarray(observation, dtype=lay.obs_dtype)
        act = np.asarray(action, dtype=lay.action_dtype)
        head = _HEAD.pack(self.episode, t, goal_token, goal, blend_w, now)
        tail = report.to_json() if report is not None else b""
        self.new_records.append(head + obs.tobytes() + act.tobytes() + tail)
        self.recorded += 1
        return True

    def written(self) -> None:
        """The store wrote the change in flight: keep its entries (in memory) and clear them."""
        if self.timeline is not None:
            self.timeline += self.new_timeline
        if self.records is not None:
            self.records += self.new_records
        self.new_timeline, self.new_records, self.last_changed = [], [], False

    # ----- stored form ----------------------------------------------------------------------------------------
    def meta(self) -> dict | None:
        """What creation stores of the recording (None when the session does not record)."""
        if self.layout is None:
            return None
        return {"max_steps": self.max_steps, **self.layout.to_dict()}

    def state(self) -> dict:
        """The counters a change stores: episode, timeline entries, and steps recorded (when recording)."""
        d = {"ep": self.episode, "tn": self.entries}
        if self.layout is not None:
            d["rn"] = self.recorded
        return d

    @classmethod
    def restore(cls, record_meta: dict | None, state: dict, last: bytes | None) -> Ledger:
        """The ledger of a session read back from a shared store (no entries: those stay in the store)."""
        layout = Layout.from_dict(record_meta) if record_meta else None
        return cls(
            episode=int(state.get("ep", 0)),
            last=orjson.loads(last) if last else None,
            entries=int(state.get("tn", 0)),
            layout=layout,
            max_steps=int(record_meta["max_steps"]) if record_meta else 0,
            recorded=int(state.get("rn", 0)),
        )


def decode_timeline(entries: list[bytes]) -> list[dict]:
    """Timeline entries as dicts (the internal index `n` and count `k` dropped)."""
    out = []
    for raw in entries:
        e = orjson.loads(raw)
        e.pop("n", None)
        e.pop("k", None)
        out.append(e)
    return out


def decode_records(layout: Layout, records: list[bytes]) -> dict[str, np.ndarray]:
    """The per-step columns of a recording (`gmt.common.recording`) from its step records.

    A record's report (the client's, sent with the act of step t) describes the action of step t - 1 of the same
    episode: it is moved to that row.
    """
    n = len(records)
    a: dict[str, np.ndarray] = {
        "episode": np.zeros(n, np.int64),
        "t": np.zeros(n, np.int64),
        "time": np.zeros(n, np.float64),
        "observations": np.zeros((n, *layout.obs_shape), layout.obs_dtype),
        "actions": np.zeros((n, *layout.action_shape), layout.action_dtype),
        "goals": np.zeros(n, np.int64),
        "goal_tokens": np.zeros(n, np.int64),
        "blend_w": np.zeros(n, np.float32),
        "reported": np.zeros(n, bool),
        "rewards": np.full(n, np.nan),
        "terminated": np.zeros(n, bool),
        "truncated": np.zeros(n, bool),
    }
    infos: dict[str, np.ndarray] = {}
    o0 = _HEAD.size
    a0 = o0 + layout.obs_bytes
    r0 = a0 + layout.action_bytes
    odt, adt = np.dtype(layout.obs_dtype), np.dtype(layout.action_dtype)
    for i, raw in enumerate(records):
        ep, t, token, goal, w, now = _HEAD.unpack_from(raw)
        a["episode"][i], a["t"][i], a["goal_tokens"][i], a["goals"][i], a["blend_w"][i], a["time"][i] = (
            ep,
            t,
            token,
            goal,
            w,
            now,
        )
        a["observations"][i] = np.frombuffer(
            raw, odt, count=layout.obs_bytes // odt.itemsize, offset=o0
        ).reshape(layout.obs_shape)
        a["actions"][i] = np.frombuffer(
            raw, adt, count=layout.action_bytes // adt.itemsize, offset=a0
        ).reshape(layout.action_shape)
        if len(raw) > r0 and i > 0 and a["episode"][i - 1] == ep and a["t"][i - 1] == t - 1:
            rep = orjson.loads(raw[r0:])
            j = i - 1
            a["reported"][j] = True
            if "r" in rep:
                a["rewards"][j] = rep["r"]
            a["terminated"][j] = bool(rep.get("te", False))
            a["truncated"][j] = bool(rep.get("tr", False))
            for k, v in rep.get("i", {}).items():
                col = infos.get(k)
                if col is None:
                    col = infos[k] = np.full(n, np.nan)
                col[j] = v
    a |= {INFO_PREFIX + k: v for k, v in sorted(infos.items())}
    return a


def assemble(meta: dict, layout: Layout, timeline: list[bytes], records: list[bytes]) -> Recording:
    """A `Recording` from the session's description (`meta`: the format's metadata fields) and its entries."""
    full = {
        "format": FORMAT,
        "version": VERSION,
        **meta,
        "steps": len(records),
        "timeline": decode_timeline(timeline),
    }
    return Recording(full, decode_records(layout, records))


def record_drawn(session_id: str, share: float) -> bool:
    """Whether `--record-share` draws this session: a fixed function of its id (a retried create agrees)."""
    if share <= 0:
        return False
    if share >= 1:
        return True
    h = int.from_bytes(hashlib.sha256(session_id.encode()).digest()[:8], "big")
    return h < share * 2**64
