"""A session as bytes without pickle: JSON for its own fields, and the context's own encoding (raw arrays)."""

from __future__ import annotations

import json

from model.context import Context, StoredContext, StoredContextError
from service.sessions import Session

FORMAT_VERSION = 2


class CodecError(ValueError):
    """Stored bytes do not describe a session."""


def encode(session: Session) -> dict[str, bytes]:
    """Hash fields: `meta` (JSON: id, model, times), `ver` (the context's version as decimal text) and the
    context's own fields (`StoredContext.to_fields`)."""
    ctx = session.ctx
    stored = ctx.to_stored() if isinstance(ctx, Context) else ctx
    meta = {
        "v": FORMAT_VERSION,
        "id": session.id,
        "model": session.model,
        "created_at": session.created_at,
        "last_used": session.last_used,
        "request": session.request,
    }
    return {
        "meta": json.dumps(meta, separators=(",", ":")).encode(),
        "ver": str(stored.version).encode(),  # what a compare-and-set write checks
        **stored.to_fields(),
    }


def decode(fields: dict[bytes | str, bytes]) -> Session:
    """Inverse of `encode` (keys may be bytes, as redis-py returns them); the context comes back stored.

    Raises:
        CodecError: the fields do not describe a session of this format.
    """
    f = {(k.decode() if isinstance(k, bytes) else k): v for k, v in fields.items()}
    try:
        meta = json.loads(f["meta"])
        if meta.get("v") != FORMAT_VERSION:
            raise CodecError(f"session format v{meta.get('v')} is not v{FORMAT_VERSION}")
        return Session(
            id=meta["id"],
            model=meta["model"],
            ctx=StoredContext.from_fields(f),
            created_at=float(meta["created_at"]),
            last_used=float(meta["last_used"]),
            request=str(meta.get("request", "")),
        )
    except CodecError:
        raise
    except (StoredContextError, KeyError, TypeError, ValueError, AttributeError) as e:
        raise CodecError(f"unreadable session: {type(e).__name__}: {e}") from e
