"""Behaviour snapshots say what kind they are, and `load_behaviour` reads each with its kind's loader."""

import json

import gymnasium as gym
import pytest
import torch

from gmt.datagen.behaviour import (
    BEHAVIOUR_DIR,
    BehaviourMeta,
    BehaviourPolicy,
    load_behaviour,
    save_behaviour,
    snapshot_kind,
)
from gmt.datagen.fixtures import random_behaviour


def test_a_written_snapshot_records_its_kind(tmp_path):
    path = random_behaviour(tmp_path, "slow", 1.0, 0)
    assert json.loads(path.with_suffix(".json").read_text())["kind"] == "actor"
    policy = load_behaviour(path, gym.make("HalfCheetah-v5").action_space)
    assert isinstance(policy, BehaviourPolicy) and policy.meta.kind == "actor"


def test_snapshots_without_a_kind_are_read_by_their_extra(tmp_path):
    """Snapshots written before `kind` existed: the committed Hopper one, and an Ant gait level with its key removed."""
    from gmt.datagen.gait import GaitPolicy

    meta = json.loads((BEHAVIOUR_DIR / "ant" / "slow.json").read_text())
    del meta["kind"]
    ant = tmp_path / "ant" / "slow.json"
    ant.parent.mkdir()
    ant.write_text(json.dumps(meta))
    ant.with_suffix(".safetensors").write_bytes((BEHAVIOUR_DIR / "ant" / "slow.safetensors").read_bytes())
    hopper = BEHAVIOUR_DIR / "hopper" / "slow.json"
    assert "kind" not in json.loads(hopper.read_text())
    assert isinstance(load_behaviour(ant, gym.make("Ant-v5").action_space), GaitPolicy)
    assert isinstance(load_behaviour(hopper, gym.make("Hopper-v5").action_space), BehaviourPolicy)
    meta = BehaviourMeta("Hopper-v5", "x", [], "tanh", [], [], extra={"command": 1.0})
    assert snapshot_kind(meta) == "actor"


def test_a_kind_without_a_loader_is_refused(tmp_path):
    meta = BehaviourMeta("Hopper-v5", "x", [], "tanh", [], [], kind="teleoperated")
    save_behaviour(tmp_path / "x", {"log_std": torch.zeros(3)}, meta)
    with pytest.raises(ValueError, match="no loader for behaviour snapshots of kind 'teleoperated'"):
        load_behaviour(tmp_path / "x", gym.make("Hopper-v5").action_space)


def test_the_snapshot_module_imports_no_kind_it_does_not_define():
    import subprocess
    import sys

    code = "import sys, gmt.datagen.behaviour; print(sorted(m for m in sys.modules if m.startswith('gmt.datagen')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "gmt.datagen.gait" not in out and "governor" not in out and "stable_baselines3" not in out, out
