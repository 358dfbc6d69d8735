"""A Breakout episode driven through a real server on loopback: preprocessed frames (uint8 [4, 84, 84]) travel
as tensors over REST (base64) and gRPC (bytes), the discrete actions come back, and every transport agrees."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from gmt.client.grpc import GrpcClient
from gmt.client.rest import RestClient
from gmt.client.runner import RunConfig, run
from gmt.model.fixtures import tiny_checkpoint

pytest.importorskip("ale_py")
pytest.importorskip("cv2")  # AtariPreprocessing

FRAMES = gym.spaces.Box(0, 255, (4, 84, 84), np.uint8)  # 4 stacked 84 x 84 grayscale frames
STEPS = 40
PREPROCESSING = {
    "screen_size": 84,
    "stack": 4,
    "frame_skip": 4,
    "noop_max": 30,
    "repeat_action_probability": 0.25,
}


@pytest.fixture(scope="module")
def breakout_server(tmp_path_factory, serve_root):
    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(
        root / "tiny-breakout",
        env_id="ALE/Breakout-v5",
        name="tiny-breakout",
        observation_space=FRAMES,
        statistic="return",
        context_length=4,
        preprocessing=PREPROCESSING,
    )
    return serve_root(root)


@pytest.fixture(scope="module")
def episodes(breakout_server):
    out = {}
    for kind in ("rest", "grpc", "grpc-stream"):
        cfg = RunConfig(
            env_id="ALE/Breakout-v5",
            model="tiny-breakout",
            goal="high",
            steps=STEPS,
            seed=3,
            transport=kind,
        )
        client = (
            RestClient(breakout_server.rest_url)
            if kind == "rest"
            else GrpcClient(breakout_server.grpc_target, stream=kind == "grpc-stream")
        )
        with client as c:
            out[kind] = run(c, cfg, echo=lambda _: None)[0]
    return out


@pytest.mark.parametrize("kind", ["rest", "grpc", "grpc-stream"])
def test_frames_go_out_and_discrete_actions_come_back(episodes, kind):
    trace = episodes[kind].trace
    assert len(trace) == STEPS or episodes[kind].terminated
    assert trace.server_step == list(range(len(trace)))  # every frame was one step of the session
    assert all(isinstance(a, int) and 0 <= a < 4 for a in trace.action)
    assert len(set(trace.action)) > 1  # sampled from the logits (expert mode), not a constant


@pytest.mark.parametrize("kind", ["rest", "grpc"])
def test_the_model_spec_declares_its_preprocessing(breakout_server, kind):
    client = (
        RestClient(breakout_server.rest_url) if kind == "rest" else GrpcClient(breakout_server.grpc_target)
    )
    with client as c:
        spec = c.get_model("tiny-breakout")
    assert spec.preprocessing == PREPROCESSING
    assert spec.action_modes == ["expert", "argmax", "sample"]  # discrete: expert first (paper A.1.3)


def test_every_transport_answers_the_same_actions(episodes):
    rest, grpc_, stream = (np.asarray(episodes[k].trace.action) for k in ("rest", "grpc", "grpc-stream"))
    assert np.array_equal(rest, grpc_) and np.array_equal(rest, stream)
