"""`gmt.service.grpc.convert`: act results built in place read back as the messages built whole did, and
observations read from a repeated field keep their values."""

from __future__ import annotations

import numpy as np
import pytest

from gmt.service.errors import InvalidArgument, NotFound
from gmt.service.grpc import convert
from gmt.service.views import ActResult
from gmt.v1 import policy_pb2 as pb


def _result(**kw) -> ActResult:
    base = dict(action=[0.25, -1.0, 0.5], discrete_action=None, step=7, goal=2, session_id="s-1")
    return ActResult(**{**base, **kw})


def test_a_continuous_act_answer_filled_in_place_carries_every_field():
    out = pb.ControlResponse()
    convert.fill_act_response(out.act, _result())
    assert out.WhichOneof("result") == "act"
    assert list(out.act.action) == [0.25, -1.0, 0.5]
    assert (out.act.step, out.act.goal, out.act.session_id, out.act.is_discrete) == (7, 2, "s-1", False)
    assert convert.act_response(_result()) == out.act


def test_a_discrete_act_answer_is_marked_discrete_even_for_action_zero():
    r = convert.act_response(_result(action=None, discrete_action=0))
    assert r.is_discrete and r.discrete_action == 0 and not r.action


def test_act_batch_items_are_the_action_or_the_error_in_order():
    answer = pb.ActBatchResponse()
    convert.add_act_batch_result(answer, "s-1", _result())
    convert.add_act_batch_result(answer, "gone", NotFound("session 'gone' not found"))
    convert.add_act_batch_result(answer, "x" * 10_000, InvalidArgument("bad id"))
    first, second, third = answer.results
    assert (
        first.session_id == "s-1"
        and first.action.step == 7
        and list(first.action.action) == [0.25, -1.0, 0.5]
    )
    assert second.WhichOneof("outcome") == "error" and second.session_id == "gone"
    assert (second.error.code, second.error.message) == ("not_found", "session 'gone' not found")
    assert third.session_id == ""  # an id too long to name a session is not echoed


@pytest.mark.parametrize("values", [[], [0.1, -2.5, 3e38], list(np.linspace(-1, 1, 17))])
def test_an_observation_of_values_is_float32_with_the_same_values(values):
    x = convert.observation(pb.ActRequest(values=pb.FloatVector(values=values)))
    assert x.dtype == np.float32
    np.testing.assert_array_equal(x, np.asarray(values, dtype=np.float32))


def test_an_act_without_an_observation_is_refused():
    with pytest.raises(InvalidArgument, match="observation is required"):
        convert.observation(pb.ActRequest(session_id="s"))
