"""A session as Redis hash fields, without pickle, written step by step.

Fields (format 3):
- `meta`: JSON written once at creation: id, model, the model version and its checkpoint fingerprint (absent in
  sessions stored before versions were: the model's default version), created_at, the creating request, the
  owner (the creating key's name, `gmt.service.keys`; absent when it has none, as in sessions stored before keys
  were: anyone's), and the layout of a step record (`H` held steps, the state's and the action's dtype and shape);
- `ver`: the compare-and-set token `<version>@<created_at>` (a session created again under the same id never
  matches a copy of its predecessor);
- `st`: JSON of the context's scalars (goal, step, blend, mode, seed, version), `last_used` and `activity` (acts/s,
  last latency and replica of the console's listing, `activity`: as of the act before the write);
- `r:<t mod H>`: the record of held step `t`: t, goal token, blend target and weight, state, action, as raw
  little-endian bytes;
- `tl`: the last entry of the session's goal timeline (JSON, `gmt.service.records`), written with each entry.
`meta` also holds `record` (the step layout and the maximum length) when the session records, and `st` the
ledger's counters (episode, timeline entries, steps recorded). The timeline's entries and the recording's step
records are lists beside the hash (`timeline_appends`, written by the same script call as the change).

An act writes `ver`, `st` and its one new record; a goal change or a reset writes `ver`, `st` and `tl`. Reading a session
back gathers the records of its last `min(step, H)` steps, each checked to be the step its slot should hold, into
a `StoredContext`: exactly the context a replica needs to continue the session.
"""

from __future__ import annotations

import dataclasses
import functools
import struct
import sys

import numpy as np
import orjson

from gmt.model.context import Context, StoredContext
from gmt.service.activity import Activity
from gmt.service.records import Ledger
from gmt.service.sessions import Session

FORMAT_VERSION = 3
_ARRAYS = ("goals", "blend_to", "blend_w", "states", "actions")
SCALARS = tuple(f.name for f in dataclasses.fields(StoredContext) if f.name not in _ARRAYS)
_HEAD = struct.Struct("<qqqf")  # t, goal token, blend target, blend weight: the record's first fields
_LITTLE = sys.byteorder == "little"


class CodecError(ValueError):
    """Stored fields do not describe a session."""


def cas_token(session: Session, version: int) -> bytes:
    """The value of `ver` for `session` at `version`."""
    return b"%d%b" % (version, _stamp(session.created_at))


@functools.lru_cache(maxsize=1 << 16)
def _stamp(created_at: float) -> bytes:
    """`@<created_at>` of `cas_token` (the float's repr: the same token whatever the version)."""
    return f"@{created_at!r}".encode()


def _record_dtype(layout: dict) -> np.dtype:
    (sd, ss), (ad, ash) = layout["state"], layout["action"]
    return _record_of(sd, tuple(ss), ad, tuple(ash))


@functools.lru_cache(maxsize=64)
def _record_of(sd: str, ss: tuple, ad: str, ash: tuple) -> np.dtype:
    """One step's record: t, goal token, blend target and weight, state, action (little-endian)."""
    return np.dtype(
        [
            ("t", "<i8"),
            ("goal", "<i8"),
            ("blend_to", "<i8"),
            ("blend_w", "<f4"),
            ("state", np.dtype(sd).newbyteorder("<"), ss),
            ("action", np.dtype(ad).newbyteorder("<"), ash),
        ]
    )


def _state(session: Session, st: dict) -> bytes:
    """`st`: the context's scalars (`Context.scalars`, taken over) with the session's own."""
    st["last_used"] = session.last_used
    st["activity"] = session.activity.dump()
    st["lg"] = session.ledger.state()
    return orjson.dumps(st)


def appends(session: Session) -> tuple[list[bytes], list[bytes]]:
    """What the change in flight appends to the session's lists: (timeline entries, step records)."""
    return session.ledger.new_timeline, session.ledger.new_records


def _record(ctx: Context, t: int) -> bytes:
    """Held step `t` as a record's bytes (`_record_dtype`), written field by field: no structured array."""
    goal, blend_to, blend_w, state, action = ctx.held(t)
    if not _LITTLE:
        state, action = (
            state.astype(state.dtype.newbyteorder("<")),
            action.astype(action.dtype.newbyteorder("<")),
        )
    return _HEAD.pack(t, goal, blend_to, blend_w) + state.tobytes() + action.tobytes()


def create_fields(session: Session) -> dict[str, bytes]:
    """Every field of a new session (its live context at step 0)."""
    ctx = session.ctx
    if not isinstance(ctx, Context) or ctx.step != 0:
        raise ValueError("a session is created from a live context at step 0")
    meta = {
        "v": FORMAT_VERSION,
        "id": session.id,
        "model": session.model,
        "model_version": session.model_version,
        "fingerprint": session.fingerprint,
        "created_at": session.created_at,
        "request": session.request,
        "layout": ctx.layout(),
    }
    if session.owner:
        meta["owner"] = session.owner
    if (record := session.ledger.meta()) is not None:
        meta["record"] = record
    out = {
        "meta": orjson.dumps(meta),
        "ver": cas_token(session, ctx.version),
        "st": _state(session, ctx.scalars()),
    }
    if session.ledger.last is not None:
        out["tl"] = orjson.dumps(session.ledger.last)
    return out


def change_fields(session: Session, since_step: int) -> dict[str, bytes]:
    """What a change wrote, for a store that holds the session up to step `since_step`: `ver`, `st`, and the
    records of the held steps from `since_step` on (all held steps when the step went back, as after a reset;
    from `session.relabelled_from` on when a goal change relabelled earlier ones)."""
    ctx = session.ctx
    if not isinstance(ctx, Context):
        raise ValueError("only a live context has changes to write")
    out = {"ver": cas_token(session, ctx.version), "st": _state(session, ctx.scalars())}
    if session.ledger.last_changed:
        out["tl"] = orjson.dumps(session.ledger.last)
    t1 = ctx.step
    if session.relabelled_from is not None:
        since_step = min(since_step, session.relabelled_from)
    for t in range(max(since_step if since_step <= t1 else 0, t1 - ctx.size), t1):
        out[f"r:{t % ctx.pool.H}"] = _record(ctx, t)
    return out


def change_fields_many(sessions: list[Session], since_steps: list[int]) -> list[dict[str, bytes]]:
    """`change_fields` of many sessions, the same bytes: the sessions whose change is one act (one new held step
    since `since_step`, nothing relabelled) are read from their pool a column at a time (`Context.scalars_of`), and
    their step records built as one array; the others one by one."""
    out: list = [None] * len(sessions)
    pools: dict[int, tuple] = {}  # id(pool) -> (pool, indices into sessions)
    for i, (s, since) in enumerate(zip(sessions, since_steps, strict=True)):
        ctx = s.ctx
        if isinstance(ctx, Context) and s.relabelled_from is None and since >= 0 and ctx.step == since + 1:
            pools.setdefault(id(ctx.pool), (ctx.pool, []))[1].append(i)
        else:
            out[i] = change_fields(s, since)
    for pool, idx in pools.values():
        slots = np.fromiter((sessions[i].ctx.slot for i in idx), np.int64, len(idx))  # [n]
        t = pool.step[slots] - 1  # [n] the new held step
        pos = t % pool.H  # [n]
        rec = np.empty(len(idx), _record_of(pool.h_state.dtype.str, pool.h_state.shape[2:],
                                            pool.h_action.dtype.str, pool.h_action.shape[2:]))  # fmt: skip
        rec["t"], rec["goal"] = t, pool.h_goal[slots, pos]
        rec["blend_to"], rec["blend_w"] = pool.h_blend_to[slots, pos], pool.h_blend_w[slots, pos]
        rec["state"], rec["action"] = pool.h_state[slots, pos], pool.h_action[slots, pos]  # [n, *shape]
        raw, size = rec.tobytes(), rec.dtype.itemsize
        keys = [f"r:{p}" for p in pos.tolist()]
        for j, (i, st) in enumerate(zip(idx, Context.scalars_of(pool, slots), strict=True)):
            s = sessions[i]
            fields = {"ver": cas_token(s, st["version"]), "st": _state(s, st)}
            if s.ledger.last_changed:
                fields["tl"] = orjson.dumps(s.ledger.last)
            fields[keys[j]] = raw[j * size : (j + 1) * size]
            out[i] = fields
    return out


def decode(fields: dict[bytes | str, bytes]) -> Session:
    """The session the fields describe (keys may be bytes, as redis-py returns them), its context stored.

    Raises:
        CodecError: the fields do not describe a session of this format, or a held step's record is missing.
    """
    f = {(k.decode() if isinstance(k, bytes) else k): v for k, v in fields.items()}
    try:
        meta = orjson.loads(f["meta"])
        if meta.get("v") != FORMAT_VERSION:
            raise CodecError(f"session format v{meta.get('v')} is not v{FORMAT_VERSION}")
        st = orjson.loads(f["st"])
        layout = meta["layout"]
        H, dtype = int(layout["H"]), _record_dtype(layout)
        step = int(st["step"])
        t = np.arange(max(step - H, 0), step)
        rec = np.zeros(len(t), dtype)
        for i, ti in enumerate(t):
            raw = f.get(f"r:{ti % H}")
            if raw is None or len(raw) != dtype.itemsize:
                raise CodecError(f"the record of step {ti} is missing or malformed")
            rec[i] = np.frombuffer(raw, dtype)[0]
            if rec[i]["t"] != ti:
                raise CodecError(f"slot {ti % H} holds step {rec[i]['t']}, not step {ti}")
        ctx = StoredContext(
            **{name: st[name] for name in SCALARS},
            goals=_native(rec["goal"]),
            blend_to=_native(rec["blend_to"]),
            blend_w=_native(rec["blend_w"]),
            states=_native(rec["state"]),
            actions=_native(rec["action"]),
        )
        return Session(
            id=meta["id"],
            model=meta["model"],
            ctx=ctx,
            created_at=float(meta["created_at"]),
            last_used=float(st["last_used"]),
            request=str(meta.get("request", "")),
            model_version=str(meta.get("model_version", "")),
            fingerprint=str(meta.get("fingerprint", "")),
            owner=str(meta.get("owner", "")),
            activity=Activity.load(st.get("activity")),
            ledger=Ledger.restore(meta.get("record"), st.get("lg", {}), f.get("tl")),
        )
    except CodecError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, orjson.JSONDecodeError) as e:
        raise CodecError(f"unreadable session: {type(e).__name__}: {e}") from e


def _native(a: np.ndarray) -> np.ndarray:
    """A record field as a contiguous array in native byte order."""
    return np.ascontiguousarray(a).astype(a.dtype.newbyteorder("="))
