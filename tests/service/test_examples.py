"""Every model's spec carries a real example observation, and the OpenAPI document's act examples are it.

The example is the environment's first observation after reset(seed=0) where the simulator is installed, else
the training data's mean observation (the checkpoint's statistics), and a hint for image models.
"""

from __future__ import annotations

import json
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

from model.fixtures import tiny_checkpoint
from service.examples import DECIMALS, example_observation
from service.rest.schemas import ExampleObservation

TOLERANCE = 10.0**-DECIMALS


def _first_observation(env_id: str) -> np.ndarray:
    env = gym.make(env_id)
    try:
        return env.reset(seed=0)[0]
    finally:
        env.close()


@pytest.mark.parametrize("model,env_id", [("tiny-gmt", "HalfCheetah-v5"), ("tiny-cartpole", "CartPole-v1")])
def test_the_spec_carries_the_first_observation_after_a_seeded_reset_and_it_acts(http, model, env_id):
    pytest.importorskip("mujoco")
    example = http.get(f"/models/{model}").json()["example_observation"]
    assert example["source"] == "reset" and f"{env_id} after reset(seed=0)" in example["description"]
    np.testing.assert_allclose(example["observation"], _first_observation(env_id), atol=TOLERANCE, rtol=0)
    sid = http.post("/sessions", json={"model": model, "goal": 0}).json()["session_id"]
    r = http.post(f"/sessions/{sid}/act", json={"observation": example["observation"]})
    assert r.status_code == 200, r.text


def test_without_the_simulator_the_example_is_the_training_datas_mean_observation(tmp_path):
    tiny_checkpoint(tmp_path / "tiny-gmt")
    code = (
        "import json, sys\n"
        "sys.modules['mujoco'] = None  # as on a server with the serve extra alone: no MuJoCo\n"
        "from model.checkpoint import load_checkpoint\n"
        "from service.examples import example_observation\n"
        f"e = example_observation(load_checkpoint({str(tmp_path / 'tiny-gmt')!r}))\n"
        "print(json.dumps(e.__dict__))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    example = json.loads(out.stdout.splitlines()[-1])
    assert example["source"] == "mean" and "normalisation statistics" in example["description"]
    mean = tiny_checkpoint().obs_norm.mean  # the same seeded statistics
    np.testing.assert_allclose(example["observation"], mean, atol=TOLERANCE, rtol=0)
    assert not np.allclose(example["observation"], 0)  # not the zeros every example used to send


def test_an_image_model_gets_a_hint_instead_of_a_frame():
    pytest.importorskip("ale_py")
    frames = gym.spaces.Box(0, 255, (4, 84, 84), np.uint8)
    ckpt = tiny_checkpoint(env_id="ALE/Breakout-v5", observation_space=frames, statistic="return")
    example = example_observation(ckpt)
    assert example.source == "hint" and example.observation is None
    assert (
        '"dtype": "uint8", "shape": [4, 84, 84]' in example.description
        and "28224 raw bytes" in example.description
    )
    assert ExampleObservation(**example.__dict__).observation is None  # what GET /models/{name} answers
    assert len(json.dumps(example.__dict__)) < 500  # small: no frame


def test_openapi_act_examples_are_each_models_example_and_are_accepted(http):
    doc = http.get("/openapi.json").json()
    act = doc["paths"]["/sessions/{session_id}/act"]["post"]["requestBody"]["content"]["application/json"]
    many = doc["paths"]["/act"]["post"]["requestBody"]["content"]["application/json"]
    assert set(act["examples"]) == set(many["examples"]) == {"tiny-gmt", "tiny-sampled", "tiny-cartpole"}
    for model, shown in act["examples"].items():
        example = http.get(f"/models/{model}").json()["example_observation"]
        assert shown["value"] == {"observation": example["observation"]}
        assert example["description"] in shown["summary"]
        assert many["examples"][model]["value"]["requests"][0]["observation"] == example["observation"]
        sid = http.post("/sessions", json={"model": model, "goal": 0}).json()["session_id"]
        r = http.post(f"/sessions/{sid}/act", json=shown["value"])  # what Swagger UI's "Try it out" sends
        assert r.status_code == 200, r.text
        item = {**many["examples"][model]["value"]["requests"][0], "session_id": sid}
        r = http.post("/act", json={"requests": [item]})
        assert r.status_code == 200 and "action" in r.json()["results"][0], r.text
