"""Objects named "module:attribute" by the user: statistics (`gmt.common.statistics`) and collection policies
(`gmt.datagen.user_policy`)."""

from __future__ import annotations

import sys
from importlib import import_module
from pathlib import Path
from typing import Any


def load_attribute(module: str, name: str) -> Any:
    """`module.name`, the module importable as by `python -m`: installed, or beside the user (the current
    directory is tried when the module is not found elsewhere).

    Raises:
        ImportError: The module cannot be imported.
        AttributeError: It has no such attribute.
    """
    try:
        mod = import_module(module)
    except ModuleNotFoundError:
        cwd = str(Path.cwd())
        if cwd in sys.path:
            raise
        sys.path.insert(0, cwd)
        mod = import_module(module)
    return getattr(mod, name)
