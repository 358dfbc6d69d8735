"""Installs by role (DESIGN.md section 8): what each extra brings, the lock that pins them, what serving imports."""

from __future__ import annotations

import re
from pathlib import Path

from gmt.common.extras import distributions, extras

ROOT = Path(__file__).resolve().parents[1]
DATA_AND_TRAINING = {
    "sklearn",
    "minari",
    "h5py",
    "scipy",
    "mujoco",
    "matplotlib",
    "stable_baselines3",
    "tensorboard",
    "gmt.datagen",
}


def _pins() -> dict[str, str]:
    lines = (ROOT / "constraints.txt").read_text().splitlines()
    pins = dict(line.split("==", 1) for line in lines if line and not line.startswith("#"))
    return {re.sub(r"[-_.]+", "-", k).lower(): v for k, v in pins.items()}


def test_constraints_pin_every_distribution_of_every_extra():
    pins = _pins()
    for extra in ["", *extras()]:
        unpinned = [d for d in distributions(extra) if d not in pins]
        assert not unpinned, f"{extra or 'base'}: {unpinned} not in constraints.txt (make constraints)"


def test_the_torch_version_is_written_only_in_the_constraints():
    version = _pins()["torch"].split("+")[0]
    assert version
    for name in ("pyproject.toml", "Makefile", "docker/Dockerfile", ".ci/run"):
        text = (ROOT / name).read_text()
        assert version not in text and not re.search(r"torch\s*[=<>~]=", text), name


def test_serving_imports_nothing_of_the_data_or_training_stack(imports_of):
    loaded = imports_of(
        "gmt.service.server",
        "gmt.service.serve_cli",
        "gmt.service.redis_store",
        "gmt.model.engine",
        "gmt.model.checkpoint",
    )
    assert "torch" in loaded and not loaded & DATA_AND_TRAINING
