"""The container tests run last, and their images start building as soon as the tests are collected: a cold build
(a Debian base, Redis and nginx images, the gmt image: ~7 minutes here) then overlaps the rest of the suite
instead of adding to it."""

from __future__ import annotations

from pathlib import Path

import pytest
from container_engine import engine, start_prebuild

HERE = Path(__file__).parent
_prebuild = None


def pytest_collection_modifyitems(session, config, items):
    global _prebuild
    mine = [i for i in items if HERE in Path(str(i.path)).parents]
    if not mine:
        return
    others = [i for i in items if HERE not in Path(str(i.path)).parents]
    items[:] = others + mine
    if config.option.collectonly:
        return
    name, _ = engine()
    if name is not None and others and _prebuild is None:
        _prebuild = start_prebuild(name)


@pytest.fixture(scope="session")
def prebuilt():
    """Wait for the background build, if one was started (its failure shows again when the test builds)."""
    if _prebuild is not None:
        _prebuild.wait()
