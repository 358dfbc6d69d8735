"""Named keys and who owns a session: the one rule of ownership, for both transports.

A server started with `--auth-tokens FILE` (`GMT_AUTH_TOKENS`) and/or `--auth-token` answers each bearer token as a
named key (`--auth-token` is the key `default`); `--admin-token` is the key `admin`, which sees every session. The
adapters authenticate a call with `Keyring.identify` and run it as that caller (`acting_as`); the core reads the
caller (`current`) where a session is created (its owner) and wherever one is read (`visible`; if not, the core
answers what the store answers for an id it never held).

- A session belongs to the key that created it. Another key is answered as if it did not exist (not found, never
  permission denied: an id's existence is not revealed) and does not see it in the listing.
- The admin key, and every caller of a server without keys, sees and may act on every session.
- A session without an owner (created by a server without keys, or stored before keys were) is anyone's.

The key file: one key a line, `name:token`; blank lines and lines starting with `#` are ignored. A name is 1 to 64
of `A-Z a-z 0-9 . _ -` (not `admin`, nor `default` beside `--auth-token`); a token 1 to 4096 printable ASCII
characters without spaces. No two keys share a name or a token. No token is ever logged or quoted in an error.
"""

from __future__ import annotations

import contextlib
import re
import secrets
from collections.abc import Iterator
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from gmt.service.errors import Unauthenticated

if TYPE_CHECKING:
    from gmt.service.settings import Settings

ADMIN = "admin"  # the name of the admin token's key
DEFAULT = "default"  # the name of `--auth-token`'s key
_NAME = re.compile(r"[A-Za-z0-9._-]{1,64}")
_TOKEN = re.compile(r"[\x21-\x7e]{1,4096}")


@dataclass(frozen=True)
class Caller:
    """Who makes a call.

    Attributes:
        name: The key's name ('' on a server without keys): the owner of the sessions it creates.
        sees_all: It sees and may act on every session (the admin key; anyone on a server without keys).
    """

    name: str
    sees_all: bool = False


ANYONE = Caller("", sees_all=True)  # a call to a server without keys
NOBODY = Caller(
    ""
)  # a call that no adapter identified, on a server with keys: sees only sessions without owner
_caller: ContextVar[Caller | None] = ContextVar("gmt_caller", default=None)


def read_key_file(path: Path) -> dict[str, str]:
    """The keys of a key file, name -> token.

    Raises:
        ValueError: the file cannot be read or a line is not a valid key (named by its number, never quoted).
    """
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"cannot read the key file {str(path)!r}: {type(e).__name__}") from None
    keys: dict[str, str] = {}
    tokens: set[str] = set()
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        name, sep, token = line.partition(":")
        where = f"key file {str(path)!r}, line {n}"
        if not sep:
            raise ValueError(f"{where}: expected 'name:token'")
        name, token = name.strip(), token.strip()
        if not _NAME.fullmatch(name):
            raise ValueError(f"{where}: a key name is 1 to 64 of A-Z a-z 0-9 . _ -")
        if name == ADMIN:
            raise ValueError(f"{where}: the name {ADMIN!r} is the admin token's (--admin-token)")
        if not _TOKEN.fullmatch(token):
            raise ValueError(f"{where}: a token is 1 to 4096 printable ASCII characters without spaces")
        if name in keys:
            raise ValueError(f"{where}: the key {name!r} is named twice")
        if token in tokens:
            raise ValueError(f"{where}: the key {name!r} has the token of an earlier key")
        keys[name] = token
        tokens.add(token)
    if not keys:
        raise ValueError(f"the key file {str(path)!r} holds no key")
    return keys


def merge(file_keys: dict[str, str], auth_token: str | None) -> dict[str, str]:
    """The server's keys: the key file's, and `--auth-token` as the key `default`.

    Raises:
        ValueError: the file names a key `default` too, or holds the auth token.
    """
    if auth_token is None:
        return dict(file_keys)
    if DEFAULT in file_keys:
        raise ValueError(f"the key file names a key {DEFAULT!r}, which is --auth-token's: rename it")
    if auth_token in file_keys.values():
        raise ValueError("the key file holds --auth-token's token: give each key its own")
    return {**file_keys, DEFAULT: auth_token}


class Keyring:
    """The bearer tokens a server accepts, each with its caller.

    Args:
        keys: name -> token of the ordinary keys.
        admin_token: The admin token (None: none), which also opens every session route as the key `admin`
            when there are keys.
    """

    def __init__(self, keys: dict[str, str], admin_token: str | None = None) -> None:
        self._entries = [(token.encode(), Caller(name)) for name, token in keys.items()]
        if keys and admin_token is not None:
            self._entries.insert(0, (admin_token.encode(), Caller(ADMIN, sees_all=True)))

    @classmethod
    def of(cls, settings: Settings) -> Keyring:
        """The keyring of `settings` (`Settings.keys`, the admin token)."""
        admin = settings.admin_token.get_secret_value() if settings.admin_token else None
        return cls(settings.keys, admin)

    def __bool__(self) -> bool:
        """Whether calls need a key."""
        return bool(self._entries)

    def identify(self, authorization: bytes | str | None, how: str) -> Caller:
        """The caller whose token an `Authorization` value (`Bearer <token>`) carries.

        Args:
            how: How to send the token, for the error (`'Authorization: Bearer <token>'`).

        Raises:
            Unauthenticated: no bearer token, or not one of the keyring's.
        """
        if isinstance(authorization, str):
            authorization = authorization.encode("latin-1", "replace")
        if authorization is None or authorization[:7].lower() != b"bearer ":  # the scheme is case-insensitive
            raise Unauthenticated(f"missing bearer token: send {how}")
        given, found = authorization[7:].strip(), None
        for token, caller in self._entries:  # every entry compared: the time does not tell which one matched
            if secrets.compare_digest(given, token) and found is None:
                found = caller
        if found is None:
            raise Unauthenticated("invalid bearer token")
        return found


@contextlib.contextmanager
def acting_as(caller: Caller) -> Iterator[None]:
    """Run the enclosed code (and the tasks it starts) as `caller`."""
    token = _caller.set(caller)
    try:
        yield
    finally:
        _caller.reset(token)


def identified() -> Caller | None:
    """The caller an adapter identified for the running call, or None (no keys, or not a call)."""
    return _caller.get()


def current(keyed: bool) -> Caller:
    """The caller of the running call; on a server with keys (`keyed`) a call no adapter identified is `NOBODY`."""
    caller = _caller.get()
    if caller is not None:
        return caller
    return NOBODY if keyed else ANYONE


def visible(owner: str, caller: Caller) -> bool:
    """Whether `caller` may see and act on a session owned by `owner`."""
    return caller.sees_all or not owner or owner == caller.name
