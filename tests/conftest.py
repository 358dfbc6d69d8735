"""Shared fixtures: tiny random-weight checkpoints built in milliseconds."""

import json
import subprocess
import sys

import pytest
import torch

from gmt.model.fixtures import tiny_checkpoint


@pytest.fixture(autouse=True, scope="session")
def _threads():
    torch.set_num_threads(1)


@pytest.fixture
def tiny_ckpt_dir(tmp_path):
    """A saved tiny HalfCheetah-v5 checkpoint directory (3 goals, K = 5)."""
    d = tmp_path / "checkpoints" / "tiny-gmt"
    tiny_checkpoint(d)
    return d


@pytest.fixture
def imports_of():
    """imports_of("a", "b.c") -> the packages a fresh interpreter has loaded after importing them: top-level
    names, and this project's as `gmt.<package>` (e.g. {"numpy", "gmt", "gmt.client"})."""

    def run(*modules: str) -> set[str]:
        names = "{'.'.join(m.split('.')[: 2 if m.startswith('gmt.') else 1]) for m in sys.modules}"
        code = f"import json, sys\nimport {', '.join(modules)}\nprint(json.dumps(sorted({names})))"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        return set(json.loads(out))

    return run
