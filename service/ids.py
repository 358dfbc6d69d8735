"""The id rules every call that names a session or a version goes through, and the per-session lock.

One owner per rule: how a session id is checked, echoed and shortened in logs, what a client-chosen id and a version
name may be. The lock (`SessionLocks`) is the one every part of the core takes around a session's read-modify-write.
"""

from __future__ import annotations

import asyncio
import re
import weakref

from gmt.model.checkpoint import VERSION_PATTERN
from gmt.service.errors import InvalidArgument, NotFound


def short_id(sid: str) -> str:
    """A session id as logs show it: its first 8 characters (a whole id is a bearer of the session)."""
    return sid[:8] + "..." if len(sid) > 8 else sid


MAX_ID_LENGTH = 128  # the longest session id accepted (the server issues 32 hex digits)
MAX_PATH_LENGTH = 4096  # the longest checkpoint path a load accepts (Linux PATH_MAX)
# Names an HTTP client rewrites in a path (RFC 3986 5.2.4), so never a session's or a model's.
DOT_SEGMENTS = (".", "..")
# A client-chosen session id: URL-unreserved characters, one spelling in any path.
SESSION_ID_PATTERN = rf"[A-Za-z0-9._~-]{{1,{MAX_ID_LENGTH}}}"
_CLIENT_ID = re.compile(SESSION_ID_PATTERN)


def check_session_id(sid: object) -> str:
    """`sid` if it can name a session; the one owner of that rule for every call that names one.

    An id too long to be one is refused without echoing it (an attacker's 200k characters must not come back in
    a header, a message or gRPC metadata).

    Raises:
        NotFound: not a string, empty, or longer than `MAX_ID_LENGTH`.
    """
    if not isinstance(sid, str) or not sid:
        raise NotFound("session id is empty: name a session created with POST /sessions")
    if len(sid) > MAX_ID_LENGTH:
        raise NotFound(f"no session has an id of {len(sid)} characters (ids are at most {MAX_ID_LENGTH})")
    return sid


def echoed_id(sid: str) -> str:
    """`sid` as an answer may repeat it: itself when it could name a session, else "" (an item of a many-session
    act then names its index; an attacker's 200k characters never come back)."""
    return sid if isinstance(sid, str) and len(sid) <= MAX_ID_LENGTH else ""


def check_new_session_id(sid: str) -> str:
    """A client-chosen id for a new session: 1 to 128 URL-unreserved characters (letters, digits, `._~-`), not
    `.` or `..`.

    Raises:
        InvalidArgument: anything else (the id is not echoed when it is too long).
    """
    if not isinstance(sid, str) or not _CLIENT_ID.fullmatch(sid):
        shown = repr(sid) if isinstance(sid, str) and len(sid) <= MAX_ID_LENGTH else "given"
        raise InvalidArgument(
            f"session_id {shown} is not 1 to {MAX_ID_LENGTH} characters of letters, digits, '.', '_', '~' or '-'"
        )
    if sid in DOT_SEGMENTS:
        raise InvalidArgument(
            f"session_id {sid!r} cannot be addressed: HTTP clients rewrite /sessions/{sid}/act to another path"
        )
    return sid


def check_version(version: object, what: str = "version") -> str:
    """`version` if it can name a model version (1 to 64 letters, digits, '.', '_', '-').

    Raises:
        InvalidArgument: anything else.
    """
    if not isinstance(version, str) or not VERSION_PATTERN.fullmatch(version):
        shown = repr(version) if isinstance(version, str) and len(version) <= 64 else "given"
        raise InvalidArgument(f"{what} {shown} is not 1 to 64 letters, digits, '.', '_' or '-'")
    return version


class SessionLocks:
    """One `asyncio.Lock` per session id, held while a session is read, changed and written back.

    Locks live as long as someone holds or waits on them (a weak map): an idle session costs nothing.
    """

    def __init__(self) -> None:
        self._locks: weakref.WeakValueDictionary[str, asyncio.Lock] = weakref.WeakValueDictionary()

    def __call__(self, sid: str) -> asyncio.Lock:
        """The lock of session `sid`."""
        lock = self._locks.get(sid)
        if lock is None:
            lock = self._locks[sid] = asyncio.Lock()
        return lock

    def busy(self, sid: str) -> bool:
        """Whether taking the lock of session `sid` now would wait: a call holds it, or is about to (a released
        lock is handed to its first waiter, which has not run yet). A free lock that is not busy is taken without
        waiting (asyncio.Lock.acquire's fast path, whose condition this mirrors)."""
        lock = self._locks.get(sid)
        if lock is None:
            return False
        return lock.locked() or any(not w.cancelled() for w in lock._waiters or ())
