"""A session as bytes without pickle: JSON for scalars and the RNG state, raw little-endian bytes for arrays."""

from __future__ import annotations

import json

import numpy as np

from model.engine import Context
from service.sessions import Session

FORMAT_VERSION = 1
ARRAYS = ("goals", "blend_to", "blend_w", "states", "actions", "timesteps")
SCALARS = ("goal", "step", "blend_from", "blend_steps", "blend_done", "action_mode")
BIT_GENERATORS = {"PCG64": np.random.PCG64, "PCG64DXSM": np.random.PCG64DXSM}
ARRAY_KINDS = "biuf"


class CodecError(ValueError):
    """Stored bytes do not describe a session."""


def encode(session: Session) -> dict[str, bytes]:
    """Hash fields: `meta` (JSON) and one `arr:<name>` field of raw bytes per array that exists."""
    ctx = session.ctx
    arrays: dict[str, dict] = {}
    fields: dict[str, bytes] = {}
    for name in ARRAYS:
        a = getattr(ctx, name)
        if a is None:
            continue
        a = np.ascontiguousarray(a)
        le = a.dtype.newbyteorder("<")
        arrays[name] = {"dtype": le.str, "shape": list(a.shape)}
        fields[f"arr:{name}"] = a.astype(le, copy=False).tobytes()
    state = ctx.rng.bit_generator.state
    if state.get("bit_generator") not in BIT_GENERATORS:
        raise CodecError(f"cannot store a {state.get('bit_generator')} generator; use np.random.default_rng")
    meta = {
        "v": FORMAT_VERSION,
        "id": session.id,
        "model": session.model,
        "created_at": session.created_at,
        "last_used": session.last_used,
        "ctx": {k: getattr(ctx, k) for k in SCALARS},
        "rng": state,
        "arrays": arrays,
    }
    fields["meta"] = json.dumps(meta, separators=(",", ":")).encode()
    return fields


def _array(desc: dict, raw: bytes | None, name: str) -> np.ndarray:
    dt = np.dtype(desc["dtype"])
    if dt.kind not in ARRAY_KINDS or raw is None:
        raise CodecError(f"array {name}: bad dtype {dt} or missing bytes")
    shape = tuple(int(s) for s in desc["shape"])
    if int(np.prod(shape)) * dt.itemsize != len(raw):
        raise CodecError(f"array {name}: {len(raw)} bytes do not fill shape {shape} of {dt}")
    return np.frombuffer(raw, dtype=dt).reshape(shape).astype(dt.newbyteorder("="))


def decode(fields: dict[bytes | str, bytes]) -> Session:
    """Inverse of `encode` (keys may be bytes, as redis-py returns them).

    Raises:
        CodecError: the fields do not describe a session of this format.
    """
    try:
        return _decode({(k.decode() if isinstance(k, bytes) else k): v for k, v in fields.items()})
    except CodecError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise CodecError(f"unreadable session: {type(e).__name__}: {e}") from e


def _decode(f: dict[str, bytes]) -> Session:
    meta = json.loads(f["meta"])
    if meta.get("v") != FORMAT_VERSION:
        raise CodecError(f"session format v{meta.get('v')} is not v{FORMAT_VERSION}")
    state = meta["rng"]
    bitgen = BIT_GENERATORS.get(state.get("bit_generator"))
    if bitgen is None:
        raise CodecError(f"unsupported bit generator {state.get('bit_generator')!r}")
    bg = bitgen()
    bg.state = state
    ctx = Context(goal=int(meta["ctx"]["goal"]), rng=np.random.Generator(bg))
    for k in SCALARS[1:]:
        setattr(ctx, k, meta["ctx"][k])
    for name, desc in meta["arrays"].items():
        if name not in ARRAYS:
            raise CodecError(f"unknown array {name!r}")
        setattr(ctx, name, _array(desc, f.get(f"arr:{name}"), name))
    return Session(
        id=meta["id"],
        model=meta["model"],
        ctx=ctx,
        created_at=float(meta["created_at"]),
        last_used=float(meta["last_used"]),
    )
