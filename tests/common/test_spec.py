"""The one definition of each shared record: REST schemas, proto messages and client types carry its fields."""

from __future__ import annotations

from dataclasses import fields

import pytest

from gmt.client import base
from gmt.common.spec import GoalInfo, SessionInfo, field_docs
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


def test_set_goal_answer_adds_the_left_out_field():
    assert set(schemas.SetGoalOut.model_json_schema()["properties"]) == names(SessionInfo)


@pytest.mark.parametrize(("record", "rest", "message", "left_out"), RECORDS)
def test_every_field_is_documented_once(record, rest, message, left_out):
    docs = field_docs(record)
    assert all(docs.values()), docs
    props = rest.model_json_schema()["properties"]
    for name in names(record) - left_out:
        assert props[name]["description"] == docs[name]


def test_clients_server_and_model_use_the_one_definition():
    assert base.SessionInfo is SessionInfo and base.GoalInfo is GoalInfo
    assert views.SessionView is SessionInfo and Goal is GoalInfo


def test_session_converts_both_ways_unchanged():
    from gmt.client.grpc import session_from_proto
    from gmt.client.rest import session_from_json

    v = SessionInfo("s", "m", 2, "high", 7, 5, 3, 1, 60.0, 12.5, "sample", (1, 1, 2), "v2", True, 8)
    assert session_from_proto(convert.session_info(v)) == v
    assert session_from_json(schemas.SetGoalOut.of(v).model_dump(mode="json")) == v
    plain = SessionInfo("s", "m", 2, context_goals=(2,))
    assert session_from_proto(convert.session_info(plain)) == plain
    assert "effective_step" not in schemas.SessionOut.of(plain).model_dump()
