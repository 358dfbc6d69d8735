"""Which of the install's extras are present, read from the installed package's own metadata (pyproject.toml).

`gmt` works with whatever is installed: a command whose extra is missing says which one to install instead of
failing with an ImportError. The extras are defined once, in pyproject.toml; this module only reads them.
"""

from __future__ import annotations

import re
from functools import cache
from importlib import metadata

DIST = "gmt-service"
_NAME = re.compile(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[([^\]]*)\])?")
_EXTRA = re.compile(r"""extra\s*==\s*['"]([^'"]+)['"]""")


class MissingExtra(RuntimeError):
    """What a command needs is not installed; the message names the extra to install."""

    def __init__(self, extra: str, what: str, missing: list[str]) -> None:
        self.extra, self.missing = extra, missing
        super().__init__(
            f"{what} needs the `{extra}` extra ({', '.join(missing)} not installed): "
            f"pip install '{DIST}[{extra}]' (in a checkout, at the tested versions: pip install -c constraints.txt "
            f"-e '.[{extra}]')"
        )


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


@cache
def installed(name: str) -> bool:
    """Whether distribution `name` is installed."""
    try:
        metadata.distribution(name)
    except metadata.PackageNotFoundError:
        return False
    return True


@cache
def requirements() -> dict[str, list[tuple[str, tuple[str, ...]]]]:
    """{extra ("" for the base install): [(distribution, its extras), ...]} as declared by this package."""
    out: dict[str, list[tuple[str, tuple[str, ...]]]] = {}
    for req in metadata.requires(DIST) or []:
        spec, _, marker = req.partition(";")
        m = _NAME.match(spec)
        if m is None:
            continue
        found = _EXTRA.search(marker)
        extras = tuple(e.strip() for e in (m.group(2) or "").split(",") if e.strip())
        out.setdefault(found.group(1) if found else "", []).append((_norm(m.group(1)), extras))
    return out


def extras() -> list[str]:
    """The extras this package declares."""
    return sorted(k for k in requirements() if k)


def distributions(extra: str) -> list[str]:
    """Every distribution `extra` adds, the extras it names of this package included."""
    seen, out, todo = set(), [], [extra]
    while todo:
        e = todo.pop()
        if e in seen:
            continue
        seen.add(e)
        if e not in requirements():
            raise KeyError(
                f"the installed {DIST} declares no extra {e!r} (its extras: {', '.join(extras())}); "
                "reinstall it from the current source"
            )
        for name, sub in requirements()[e]:
            if name == _norm(DIST):
                todo.extend(sub)
            elif name not in out:
                out.append(name)
    return out


def missing(extra: str) -> list[str]:
    """The distributions of `extra` that are not installed (empty when the extra is complete).

    An extra that the installed metadata does not declare (a stale install) is reported missing as a whole.
    """
    try:
        wanted = distributions(extra)
    except KeyError:
        return [f"{DIST}[{extra}] (reinstall {DIST}: its installed metadata predates this extra)"]
    return [d for d in wanted if not installed(d)]


def require(extra: str, what: str) -> None:
    """Raise `MissingExtra` for `what` (e.g. "gmt serve") unless every distribution of `extra` is installed."""
    gone = missing(extra)
    if gone:
        raise MissingExtra(extra, what, gone)


def require_module(module: str, extra: str, what: str) -> None:
    """Raise `MissingExtra` unless `module` can be imported (for a feature inside an otherwise light command)."""
    from importlib.util import find_spec

    try:
        found = find_spec(module) is not None
    except ModuleNotFoundError:  # a parent package is missing
        found = False
    if not found:
        raise MissingExtra(extra, what, [module.split(".")[0]])
