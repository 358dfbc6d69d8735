"""An act may name the step it is for: a repeat is answered again without stepping, a mismatch is refused."""

import grpc
import numpy as np
import pytest

from gmt.v1 import policy_pb2 as pb

OBS = np.random.default_rng(11).normal(size=(3, 17)).astype(np.float32)


def _create(http) -> str:
    r = http.post("/sessions", json={"model": "tiny-sampled", "goal": 1, "seed": 3})
    assert r.status_code == 201, r.text
    return r.json()["session_id"]


def test_rest_repeat_is_idempotent_and_a_mismatch_names_the_step(http):
    sid = _create(http)
    first = http.post(f"/sessions/{sid}/act", json={"observation": OBS[0].tolist(), "step": 0})
    assert first.status_code == 200 and first.json()["step"] == 0
    again = http.post(f"/sessions/{sid}/act", json={"observation": OBS[0].tolist(), "step": 0})
    assert again.status_code == 200 and again.json() == first.json()  # the same answer, not a new step
    other = http.post(f"/sessions/{sid}/act", json={"observation": OBS[1].tolist(), "step": 0})
    assert other.status_code == 409 and other.json()["error"]["code"] == "failed_precondition"
    assert "already answered step 0 for another observation" in other.json()["error"]["message"]
    assert http.get(f"/sessions/{sid}").json()["step"] == 1
    second = http.post(f"/sessions/{sid}/act", json={"observation": OBS[1].tolist(), "step": 1})
    assert second.status_code == 200 and second.json()["step"] == 1
    ahead = http.post(f"/sessions/{sid}/act", json={"observation": OBS[2].tolist(), "step": 5})
    assert ahead.status_code == 409 and ahead.json()["error"]["code"] == "failed_precondition"
    assert "is at step 2; this act is for step 5" in ahead.json()["error"]["message"]
    # A twin that never retried took exactly the same actions.
    twin = _create(http)
    for t in range(2):
        r = http.post(f"/sessions/{twin}/act", json={"observation": OBS[t].tolist()})
        assert r.json()["action"] == (first if t == 0 else second).json()["action"]
    assert (
        http.post(f"/sessions/{sid}/act", json={"observation": OBS[0].tolist(), "step": -1}).status_code
        == 400
    )


def test_grpc_step_field_and_act_batch(http, stub):
    sid = _create(http)
    req = pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS[0]), step=0)
    a = stub.Act(req)
    assert stub.Act(req) == a and a.step == 0
    with pytest.raises(grpc.RpcError) as e:
        stub.Act(pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS[1]), step=3))
    assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "is at step 1" in e.value.details()
    batch = stub.ActBatch(
        pb.ActBatchRequest(
            requests=[pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS[0]), step=0)]
        )
    )
    assert batch.results[0].action == a  # a repeat inside a batch is answered from the session's history
    with pytest.raises(grpc.RpcError) as e:
        stub.Act(pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS[1]), step=0))
    assert (
        e.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "another observation" in e.value.details()
    )
