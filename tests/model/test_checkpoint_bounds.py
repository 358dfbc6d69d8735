"""A checkpoint's config is checked against bounds and against its tensors' shapes before the model is built
(docs/reliability.md, "Checkpoint config"): `max_timestep` 6e6 beside a tiny model's weights once built a
6e6-row embedding (3.3 GB of RSS) before the shapes were compared; now it is a CheckpointError naming the tensor,
and the model is never built on a real device."""

from __future__ import annotations

import json

import pytest
import torch

import gmt.model.checkpoint as checkpoint_module
from gmt.model.checkpoint import CheckpointError, load_checkpoint
from gmt.model.fixtures import tiny_checkpoint


@pytest.fixture
def ckpt(tmp_path):
    tiny_checkpoint(tmp_path / "tiny")
    return tmp_path / "tiny"


def _edit(ckpt, **model) -> None:
    meta = json.loads((ckpt / "gmt.json").read_text())
    meta["model"].update(model)
    (ckpt / "gmt.json").write_text(json.dumps(meta))


@pytest.fixture
def built_on(monkeypatch) -> list[str]:
    """The device type of every model `load_checkpoint` builds."""
    devices = []
    real = checkpoint_module.GMT

    def build(cfg):
        devices.append(torch.empty(0).device.type)
        return real(cfg)

    monkeypatch.setattr(checkpoint_module, "GMT", build)
    return devices


def test_a_config_larger_than_its_tensors_is_refused_before_the_model_is_built(ckpt, built_on):
    load_checkpoint(ckpt)
    assert built_on[-1] == "cpu"
    built_on.clear()
    _edit(ckpt, max_timestep=6_000_000)
    with pytest.raises(CheckpointError, match=r"time_emb.weight \[1024, 32\] \(config: \[6000000, 32\]\)"):
        load_checkpoint(ckpt)
    assert "cpu" not in built_on, f"the model was built before the shapes were compared: {built_on}"


def test_missing_and_unexpected_tensors_are_named_briefly(ckpt):
    _edit(ckpt, n_layer=100)
    with pytest.raises(CheckpointError, match=r"tensors missing \[") as e:
        load_checkpoint(ckpt)
    assert len(str(e.value)) < 1000


@pytest.mark.parametrize(
    "field, value",
    [
        ("max_timestep", 10**9),
        ("n_embd", 1 << 20),
        ("n_layer", 10**4),
        ("context_length", 10**6),
        ("n_goals", 10**7),
    ],
)
def test_a_config_out_of_bounds_is_refused_by_name(ckpt, built_on, field, value):
    _edit(ckpt, **{field: value})
    with pytest.raises(CheckpointError, match=field):
        load_checkpoint(ckpt)
    assert "cpu" not in built_on
