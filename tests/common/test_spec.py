"""The one definition of each shared record: REST schemas, proto messages and client types carry its fields."""

from __future__ import annotations

from dataclasses import fields, replace

import pytest

from gmt.client import base
from gmt.common.spec import GoalInfo, ModelInfo, SessionInfo, field_docs
from gmt.model.goals import Goal
from gmt.service import views
from gmt.service.grpc import convert
from gmt.service.rest import schemas
from gmt.v1 import policy_pb2 as pb

# (record, REST schema, proto message, fields the REST schema leaves out)
RECORDS = [
    (GoalInfo, schemas.GoalOut, pb.Goal, set()),
    (SessionInfo, schemas.SessionOut, pb.SessionInfo, {"effective_step"}),  # only a goal change answers it
]


def names(record: type) -> set[str]:
    return {f.name for f in fields(record)}


@pytest.mark.parametrize(("record", "rest", "message", "left_out"), RECORDS)
def test_rest_and_proto_carry_every_field(record, rest, message, left_out):
    assert set(rest.model_json_schema()["properties"]) == names(record) - left_out
    assert {f.name for f in message.DESCRIPTOR.fields} == names(record)


VERSIONS = {"versions", "default_version", "canary"}  # the server's version table, beside the model record


def test_model_rest_and_proto_carry_every_field():
    record = names(ModelInfo)
    assert set(schemas.ModelOut.model_json_schema()["properties"]) == record | VERSIONS | {
        "discrete_actions",  # REST only: the proto's action_space says it
        "example_observation",  # REST only: an observation to try
    }
    assert {f.name for f in pb.ModelInfo.DESCRIPTOR.fields} == {
        convert.RENAMED.get(n, n) for n in record
    } | VERSIONS
    assert set(convert.RENAMED) <= record


def test_set_goal_answer_adds_the_left_out_field():
    assert set(schemas.SetGoalOut.model_json_schema()["properties"]) == names(SessionInfo)


@pytest.mark.parametrize(("record", "rest", "message", "left_out"), [*RECORDS, (ModelInfo, None, None, None)])
def test_every_field_is_documented_once(record, rest, message, left_out):
    if record is ModelInfo:
        rest, left_out = schemas.ModelOut, set()
    docs = field_docs(record)
    assert all(docs.values()), docs
    props = rest.model_json_schema()["properties"]
    for name in names(record) - left_out:
        assert props[name]["description"] == docs[name]


def test_clients_server_and_model_use_the_one_definition():
    assert base.SessionInfo is SessionInfo and base.GoalInfo is GoalInfo
    assert views.SessionView is SessionInfo and Goal is GoalInfo
    assert issubclass(views.ModelView, ModelInfo) and base.ModelInfo is ModelInfo


def test_session_converts_both_ways_unchanged():
    from gmt.client.grpc import session_from_proto
    from gmt.client.rest import session_from_json

    v = SessionInfo("s", "m", 2, "high", 7, 5, 3, 1, 60.0, 12.5, "sample", (1, 1, 2), "v2", True, 8)
    assert session_from_proto(convert.session_info(v)) == v
    assert session_from_json(schemas.SetGoalOut.of(v).model_dump(mode="json")) == v
    plain = SessionInfo("s", "m", 2, context_goals=(2,))
    assert session_from_proto(convert.session_info(plain)) == plain
    assert "effective_step" not in schemas.SessionOut.of(plain).model_dump()


def test_model_converts_both_ways_unchanged():
    from gmt.client.grpc import model_from_proto
    from gmt.client.rest import model_from_json

    box = {"type": "box", "shape": [2], "dtype": "float32", "low": [None, -1.0], "high": [None, 1.0]}
    disc = {"type": "discrete", "shape": [], "dtype": "int64", "n": 3}
    info = ModelInfo(
        "m", "Env-v0", box, disc, 8, "return", [GoalInfo(0, "low", 1.0, 0.5, 0.0, 2.0, 10)], {"frame_skip": 4},
        ["expert", "argmax"], 2,
    )  # fmt: skip
    v = views.ModelView(**{f.name: getattr(info, f.name) for f in fields(ModelInfo)}, discrete_actions=True)
    assert model_from_proto(convert.model_info(v)) == info
    got = model_from_json(schemas.ModelOut.of(v).model_dump(mode="json"))  # spaces list unset bounds as null
    assert replace(got, observation_space=box, action_space=disc) == info
    assert [
        {k: x for k, x in d.items() if x is not None} for d in (got.observation_space, got.action_space)
    ] == [
        box,
        disc,
    ]
