"""Write constraints.txt: the exact version of every distribution that any extra of gmt-service installs.

Run with the development environment's interpreter after changing a dependency (`make constraints`); every
extra must be installed there (`pip install -e '.[dev,bench,atari]'`). The versions are the installed ones, so
the lock is what the tests ran against. pip applies it with `-c constraints.txt` (Makefile, Dockerfile).
"""

from __future__ import annotations

import sys
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

DIST = "gmt-service"
HEADER = """\
# Every distribution any extra of gmt-service installs, at the version the tests ran with: the only place a
# version is written (torch is its CPU build, from the PyTorch CPU index or a local wheel). Regenerate with
# `make constraints` after changing pyproject.toml; install with `pip install -c constraints.txt '.[EXTRA]'`.
"""


def closure() -> dict[str, str]:
    """{canonical name: installed version} of everything gmt-service and all its extras require."""
    root = metadata.distribution(DIST)
    extras = set(root.metadata.get_all("Provides-Extra") or [])
    todo = [(DIST, frozenset(extras))]
    seen: dict[str, set[str]] = {}
    out: dict[str, str] = {}
    while todo:
        name, wanted = todo.pop()
        key = canonicalize_name(name)
        done = seen.setdefault(key, set())
        if key in out and wanted <= done:
            continue
        done |= wanted
        try:
            dist = metadata.distribution(name)
        except metadata.PackageNotFoundError:
            sys.exit(f"{name} is required but not installed: install every extra before locking")
        if key != DIST:
            out[key] = dist.version
        for text in dist.requires or []:
            req = Requirement(text)
            contexts = [{"extra": e} for e in wanted] or [{"extra": ""}]
            if req.marker is None or any(req.marker.evaluate(c) for c in contexts):
                todo.append((req.name, frozenset(req.extras)))
    return out


def main(path: str = "constraints.txt") -> None:
    """Write the lock to `path`."""
    pins = closure()
    lines = [f"{name}=={pins[name]}" for name in sorted(pins)]
    Path(path).write_text(HEADER + "\n".join(lines) + "\n")
    print(f"wrote {path}: {len(lines)} pins")


if __name__ == "__main__":
    main(*sys.argv[1:])
