"""Where the Redis session store keeps what (prefix `gmt:` by default).

Each session's keys are hash-tagged with its id, so that Redis Cluster keeps them on one shard: `{<id>}:s` is the
session's hash (`session_codec`: written once at creation, then only what each change changed); `{<id>}:tl` and
`{<id>}:rec` its goal timeline and its recording; `{<id>}:x` marks an expired (`1`) or closed (`closed`) session for
a day, so that it answers that rather than "not found". Beside them: `live`, the index of live sessions (the
maximum-sessions count, the expiry sweep), written only by creates, closes and sweeps, never by an act; `epoch`, a
random marker written once (when it is gone or changed, the store lost its data); `models`, a hash of each model's
default version and canary (`model_state`).
"""

from __future__ import annotations

TOMBSTONE_TTL_S = 86_400  # how long an expired or closed id answers so


class RedisKeys:
    """The key names of one store (one prefix).

    Args:
        prefix: Key prefix.
        idle_timeout_s: Sessions unused for longer expire (their keys live twice as long, `ttl_ms`).
    """

    def __init__(self, prefix: str, idle_timeout_s: float) -> None:
        self.prefix = prefix
        self.live = f"{prefix}live"
        self.epoch = f"{prefix}epoch"
        self.models = f"{prefix}models"
        # Redis key TTLs only collect sessions nobody touched for twice the idle timeout.
        self.ttl_ms = int((2 * idle_timeout_s + 60) * 1000)

    def session(self, sid: str) -> str:
        """The session's hash."""
        return f"{self.prefix}{{{sid}}}:s"

    def tomb(self, sid: str) -> str:
        """The marker of an expired or closed session."""
        return f"{self.prefix}{{{sid}}}:x"

    def timeline(self, sid: str) -> str:
        """The session's goal timeline (a list)."""
        return f"{self.prefix}{{{sid}}}:tl"

    def recording(self, sid: str) -> str:
        """The session's step records (a list)."""
        return f"{self.prefix}{{{sid}}}:rec"

    def lists(self, sid: str) -> list[str]:
        """The session's keys beside its hash: timeline, recording."""
        return [self.timeline(sid), self.recording(sid)]
