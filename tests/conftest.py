"""Shared fixtures: tiny random-weight checkpoints built in milliseconds."""

import pytest
import torch

from model.fixtures import tiny_checkpoint


@pytest.fixture(autouse=True, scope="session")
def _threads():
    torch.set_num_threads(1)


@pytest.fixture
def tiny_ckpt_dir(tmp_path):
    """A saved tiny HalfCheetah-v5 checkpoint directory (3 goals, K = 5)."""
    d = tmp_path / "checkpoints" / "tiny-gmt"
    tiny_checkpoint(d)
    return d
