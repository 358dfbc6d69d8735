"""The thin client: the clients import neither torch nor `gmt.model`, and the base install declares nothing heavy
(tests/test_installs.py installs it into fresh environments and drives a live server with it)."""

from __future__ import annotations

from pathlib import Path

from gmt.common.extras import distributions

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "scikit-learn", "minari", "stable-baselines3", "safetensors", "mujoco", "matplotlib")


def test_clients_import_neither_torch_nor_model(imports_of):
    loaded = imports_of(
        "gmt.client.rest",
        "gmt.client.grpc",
        "gmt.client.runner",
        "gmt.common.envs",
        "gmt.common.segments",
        "gmt.client.cli",
    )
    assert "torch" not in loaded and "gmt.model" not in loaded
    assert not loaded & {"sklearn", "minari", "safetensors", "stable_baselines3", "mujoco", "matplotlib"}


def test_the_base_install_declares_nothing_heavy():
    base = set(distributions(""))
    assert base and not base & set(HEAVY), base & set(HEAVY)
    assert {"torch", "safetensors"} <= set(distributions("serve"))
