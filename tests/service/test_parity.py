"""REST, unary gRPC, the Control stream and the engine itself give the same actions for the same history."""

import base64

import numpy as np

from gmt.v1 import policy_pb2 as pb


def rest_session(http, goal=0, **kw) -> str:
    r = http.post("/sessions", json={"model": "tiny-gmt", "goal": goal, **kw})
    assert r.status_code == 201, r.text
    assert r.headers["X-Session-Id"] == r.json()["session_id"]
    return r.json()["session_id"]


def rest_act(http, sid, obs) -> np.ndarray:
    r = http.post(f"/sessions/{sid}/act", json={"observation": obs.tolist()})
    assert r.status_code == 200, r.text
    assert r.headers["X-Session-Id"] == sid
    return np.asarray(r.json()["action"], dtype=np.float32)


def grpc_session(stub, goal=0) -> str:
    return stub.CreateSession(
        pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=goal))
    ).session_id


def grpc_act(stub, sid, obs) -> np.ndarray:
    r = stub.Act(pb.ActRequest(session_id=sid, values=pb.FloatVector(values=obs.tolist())))
    return np.asarray(r.action, dtype=np.float32)


def engine_actions(engine, observations, goal=0, switch=None):
    """The engine's actions for one session; `switch` = (step, goal) changes the goal before that step."""
    ctx = engine.new_context(goal)
    out = []
    for t, o in enumerate(observations):
        if switch and t == switch[0]:
            engine.set_goal(ctx, switch[1])
        out.append(engine.act([ctx], [o])[0])
    return np.stack(out)


def test_models_describe_spaces_goals_and_context(http, stub):
    models = http.get("/models").json()["models"]
    assert [m["name"] for m in models] == ["tiny-cartpole", "tiny-gmt", "tiny-sampled"]
    m = http.get("/models/tiny-gmt").json()
    assert m["env_id"] == "HalfCheetah-v5" and m["context_length"] == 5
    assert m["observation_space"]["shape"] == [17] and m["action_space"]["shape"] == [6]
    assert [(g["id"], g["name"], g["mean"]) for g in m["goals"]] == [
        (0, "low", 0.0),
        (1, "medium", 1.0),
        (2, "high", 2.0),
    ]
    g = stub.GetModel(pb.GetModelRequest(name="tiny-gmt"))
    assert g.env_id == "HalfCheetah-v5" and [x.name for x in g.goals] == ["low", "medium", "high"]
    assert list(g.action_space.low) == [-1.0] * 6
    names = [x.name for x in stub.ListModels(pb.ListModelsRequest()).models]
    assert names == ["tiny-cartpole", "tiny-gmt", "tiny-sampled"]


def test_same_actions_over_rest_grpc_stream_and_engine(http, stub, engine, observations):
    want = engine_actions(engine, observations)
    sid_rest, sid_grpc, sid_stream = rest_session(http), grpc_session(stub), grpc_session(stub)
    rest = np.stack([rest_act(http, sid_rest, o) for o in observations])
    unary = np.stack([grpc_act(stub, sid_grpc, o) for o in observations])
    reqs = [
        pb.ControlRequest(
            act=pb.ActRequest(session_id=sid_stream if t == 0 else "", values=pb.FloatVector(values=o))
        )
        for t, o in enumerate(observations.tolist())
    ]
    answers = list(stub.Control(iter(reqs)))
    stream = np.stack([np.asarray(a.act.action, dtype=np.float32) for a in answers])
    assert [a.act.step for a in answers] == list(range(len(observations)))
    np.testing.assert_array_equal(rest, want)
    np.testing.assert_array_equal(unary, want)
    np.testing.assert_array_equal(stream, want)
    assert not np.array_equal(want[0], want[1])  # the comparison has something to compare


def test_tensor_observations_match_lists(http, stub, engine, observations):
    want = engine_actions(engine, observations[:3])
    sid_rest, sid_grpc = rest_session(http), grpc_session(stub)
    for t, o in enumerate(observations[:3]):
        tensor = {"data": base64.b64encode(o.tobytes()).decode(), "dtype": "float32", "shape": [17]}
        r = http.post(f"/sessions/{sid_rest}/act", json={"observation": tensor})
        assert r.status_code == 200, r.text
        np.testing.assert_array_equal(np.float32(r.json()["action"]), want[t])
        t_pb = pb.Tensor(data=o.astype(np.float64).tobytes(), dtype="float64", shape=[17])
        a = stub.Act(pb.ActRequest(session_id=sid_grpc, tensor=t_pb))
        np.testing.assert_array_equal(np.float32(a.action), want[t])


def test_set_goal_conditions_the_next_step_on_the_new_goal(http, stub, engine, observations):
    switch_at = 6
    want_switched = engine_actions(engine, observations, switch=(switch_at, 2))
    want_kept = engine_actions(engine, observations)
    kept, switched = rest_session(http), rest_session(http)
    g_sid = grpc_session(stub)
    for t, o in enumerate(observations):
        if t == switch_at:
            r = http.put(f"/sessions/{switched}/goal", json={"goal": "high"})
            assert r.status_code == 200 and r.json()["goal"] == 2 and r.json()["goal_name"] == "high"
            info = stub.SetGoal(pb.SetGoalRequest(session_id=g_sid, goal=pb.GoalSelector(target=1.9)))
            assert info.goal == 2
        a_kept, a_switched, a_grpc = (
            rest_act(http, kept, o),
            rest_act(http, switched, o),
            grpc_act(stub, g_sid, o),
        )
        np.testing.assert_array_equal(a_kept, want_kept[t])
        np.testing.assert_array_equal(a_switched, want_switched[t])
        np.testing.assert_array_equal(a_grpc, want_switched[t])
        if t >= switch_at:
            assert not np.array_equal(a_kept, a_switched), f"step {t}: the new goal did not change the action"
        else:
            np.testing.assert_array_equal(a_kept, a_switched)
    s = http.get(f"/sessions/{switched}").json()
    # K = 5: the context holds steps 7..11, all conditioned on the new goal; the kept session never changed.
    assert s["context_goals"] == [2] * 5 and s["step"] == len(observations)
    assert http.get(f"/sessions/{kept}").json()["context_goals"] == [0] * 5
    assert list(stub.GetSession(pb.GetSessionRequest(session_id=g_sid)).context_goals) == [2] * 5


def test_goal_token_changes_exactly_at_the_switch(http, observations):
    sid = rest_session(http)
    for o in observations[:2]:
        rest_act(http, sid, o)
    assert http.put(f"/sessions/{sid}/goal", json={"goal": 1}).json()["context_goals"] == [0, 0]
    rest_act(http, sid, observations[2])
    assert http.get(f"/sessions/{sid}").json()["context_goals"] == [0, 0, 1]


def test_blend_steps_fade_the_goal_in(http, engine, observations):
    ctx = engine.new_context(0)
    want = []
    for t, o in enumerate(observations[:6]):
        if t == 2:
            engine.set_goal(ctx, 2, blend_steps=3)
        want.append(engine.act([ctx], [o])[0])
    sid = rest_session(http)
    got = []
    for t, o in enumerate(observations[:6]):
        if t == 2:
            r = http.put(f"/sessions/{sid}/goal", json={"goal": 2, "blend_steps": 3})
            assert r.json()["blend_remaining"] == 3 and r.json()["blend_from"] == 0
        got.append(rest_act(http, sid, o))
    np.testing.assert_array_equal(np.stack(got), np.stack(want))
    assert http.get(f"/sessions/{sid}").json()["blend_remaining"] == 0


def test_create_by_target_picks_the_nearest_goal_mean(http, stub):
    r = http.post("/sessions", json={"model": "tiny-gmt", "target": 1.4})
    assert r.json()["goal"] == 1 and r.json()["goal_name"] == "medium"
    s = stub.CreateSession(pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(target=-5.0)))
    assert s.goal == 0
    s = stub.CreateSession(pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(name="high")))
    assert s.goal == 2 and s.goal_name == "high"


def test_reset_starts_a_new_episode(http, stub, engine, observations):
    want = engine_actions(engine, observations[:3], goal=1)
    sid = rest_session(http, goal=0)
    for o in observations[5:9]:
        rest_act(http, sid, o)
    r = http.post(f"/sessions/{sid}/reset", json={"goal": 1})
    assert (
        r.status_code == 200
        and r.json()["step"] == 0
        and r.json()["context_size"] == 0
        and r.json()["goal"] == 1
    )
    np.testing.assert_array_equal(np.stack([rest_act(http, sid, o) for o in observations[:3]]), want)
    assert http.post(f"/sessions/{sid}/reset").json()["goal"] == 1  # no body: keep the goal
    g = grpc_session(stub, goal=1)
    grpc_act(stub, g, observations[9])
    assert stub.ResetSession(pb.ResetSessionRequest(session_id=g)).step == 0
    np.testing.assert_array_equal(np.stack([grpc_act(stub, g, o) for o in observations[:3]]), want)


def test_close_then_the_session_is_gone(http, stub):
    sid = rest_session(http)
    r = http.delete(f"/sessions/{sid}")
    assert r.status_code == 204 and r.headers["X-Session-Id"] == sid
    r = http.get(f"/sessions/{sid}")
    assert r.status_code == 404 and "not found" in r.json()["error"]["message"]
    g = grpc_session(stub)
    assert stub.CloseSession(pb.CloseSessionRequest(session_id=g)).session_id == g


def test_discrete_model_answers_integer_actions(http, stub):
    r = http.post("/sessions", json={"model": "tiny-cartpole", "goal": 0, "action_mode": "sample", "seed": 3})
    assert r.status_code == 201, r.text
    sid = r.json()["session_id"]
    a = http.post(f"/sessions/{sid}/act", json={"observation": [0.1, 0.0, -0.1, 0.2]}).json()
    assert isinstance(a["action"], int) and a["action"] in (0, 1)
    s = stub.CreateSession(pb.CreateSessionRequest(model="tiny-cartpole", goal=pb.GoalSelector(id=1)))
    out = stub.Act(
        pb.ActRequest(session_id=s.session_id, values=pb.FloatVector(values=[0.1, 0.0, -0.1, 0.2]))
    )
    assert out.is_discrete and out.discrete_action in (0, 1) and len(out.action) == 0


def test_calibrated_model_samples_by_default_identically_over_rest_grpc_and_engine(ckpt_root, http, stub):
    from gmt.model.checkpoint import load_checkpoint
    from gmt.model.engine import PolicyEngine

    assert http.get("/models/tiny-sampled").json()["action_modes"] == ["sample", "mean"]
    assert http.get("/models/tiny-gmt").json()["action_modes"] == ["mean"]
    engine = PolicyEngine(load_checkpoint(ckpt_root / "tiny-sampled"))
    obs = np.random.default_rng(3).normal(size=(6, 17)).astype(np.float32)
    ctx = engine.new_context(1, seed=11)
    want = np.stack([engine.act([ctx], [o])[0] for o in obs])
    r = http.post("/sessions", json={"model": "tiny-sampled", "goal": 1, "seed": 11})
    assert r.status_code == 201 and r.json()["action_mode"] == "sample", r.text
    rest = np.stack([rest_act(http, r.json()["session_id"], o) for o in obs])
    g = stub.CreateSession(pb.CreateSessionRequest(model="tiny-sampled", goal=pb.GoalSelector(id=1), seed=11))
    unary = np.stack([grpc_act(stub, g.session_id, o) for o in obs])
    np.testing.assert_array_equal(rest, want)
    np.testing.assert_array_equal(unary, want)
    # The mean mode is the same network without the noise.
    m = http.post("/sessions", json={"model": "tiny-sampled", "goal": 1, "action_mode": "mean"}).json()
    first = rest_act(http, m["session_id"], obs[0])
    ctx_mean = engine.new_context(1, "mean")
    np.testing.assert_array_equal(first, engine.act([ctx_mean], [obs[0]])[0])
    assert not np.array_equal(first, want[0])
