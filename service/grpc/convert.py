"""Protobuf messages to core arguments and core results to protobuf messages."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, fields

import numpy as np

from gmt.common.spec import ModelInfo
from gmt.service.errors import InvalidArgument, ServiceError
from gmt.service.ids import echoed_id
from gmt.service.observations import decode_tensor
from gmt.service.records import Report, check_report
from gmt.service.views import ActResult, GoalRef, ModelView, SessionView, TimelineView
from gmt.v1 import policy_pb2 as pb


def space(d: dict) -> pb.Space:
    """A space dict (`gmt.common.spaces`) as a message; null (infinite) bounds become +-inf."""

    def bounds(values: list | None, inf: float) -> list[float]:
        return [inf if v is None else float(v) for v in (values or [])]

    return pb.Space(
        type=d["type"],
        shape=d.get("shape", []),
        low=bounds(d.get("low"), -math.inf),
        high=bounds(d.get("high"), math.inf),
        n=d.get("n", 0),
        dtype=d.get("dtype", ""),
    )


RENAMED = {
    "preprocessing": "preprocessing_json"
}  # record field -> proto field: the proto carries a JSON string


def model_info(v: ModelView) -> pb.ModelInfo:
    """A model view as ModelInfo: every field of the model record (`gmt.common.spec.ModelInfo`), and the versions."""
    out = {f.name: getattr(v, f.name) for f in fields(ModelInfo)} | {
        "observation_space": space(v.observation_space),
        "action_space": space(v.action_space),
        "goals": [pb.Goal(**asdict(g)) for g in v.goals],
        "action_modes": list(v.action_modes),
        "preprocessing": json.dumps(v.preprocessing) if v.preprocessing else "",
    }
    return pb.ModelInfo(**{RENAMED.get(k, k): x for k, x in out.items()}, **versions(v))


def versions(v: ModelView) -> dict:
    """A model view's version table as ModelInfo fields."""
    out = {
        "versions": [pb.ModelVersion(**asdict(x)) for x in v.versions],
        "default_version": v.default_version,
    }
    if v.canary is not None:
        out["canary"] = pb.Canary(version=v.canary[0], share=v.canary[1])
    return out


def session_info(v: SessionView) -> pb.SessionInfo:
    """A session view as SessionInfo (the proto carries every field of the record under its name)."""
    return pb.SessionInfo(**{f.name: getattr(v, f.name) for f in fields(SessionView)})


def timeline(v: TimelineView) -> pb.Timeline:
    """A timeline view as a Timeline message."""

    def given(d: dict) -> pb.GoalSelector | None:
        if "target" in d:
            return pb.GoalSelector(target=d["target"])
        if "goal" in d:
            g = d["goal"]
            return pb.GoalSelector(name=g) if isinstance(g, str) else pb.GoalSelector(id=int(g))
        return None

    return pb.Timeline(
        session_id=v.session_id,
        model=v.model,
        model_version=v.model_version,
        fingerprint=v.fingerprint or "",
        step=v.step,
        episode=v.episode,
        entries=v.entries,
        offset=v.offset,
        goals=[
            pb.TimelineEntry(
                step=e["step"],
                episode=e["episode"],
                goal=e["goal"],
                given=given(e["given"]),
                blend_steps=e["blend_steps"],
                by=e["by"],
                at=e["at"],
            )
            for e in v.goals
        ],
    )


def report(req: pb.ActRequest) -> Report | None:
    """The report on the previous action an ActRequest carries (None when none).

    Raises:
        InvalidArgument: a value `records.check_report` refuses.
    """
    return check_report(
        req.reward if req.HasField("reward") else None,
        req.terminated if req.HasField("terminated") else None,
        req.truncated if req.HasField("truncated") else None,
        dict(req.info) if len(req.info) else None,
    )


def act_response(r: ActResult) -> pb.ActResponse:
    """An act result as ActResponse."""
    out = pb.ActResponse()
    fill_act_response(out, r)
    return out


def fill_act_response(out: pb.ActResponse, r: ActResult) -> None:
    """Write an act result into `out` (a field of the message that carries it: no copy of a built message)."""
    if r.action is None:
        out.discrete_action, out.is_discrete = r.discrete_action, True
    else:
        out.action.extend(r.action)
    out.step, out.goal, out.session_id = r.step, r.goal, r.session_id


def add_act_batch_result(into: pb.ActBatchResponse, session_id: str, r: ActResult | ServiceError) -> None:
    """Append one item to an ActBatchResponse, built in place: the action, or the error (its code and message)
    that failed it (an id too long to name a session is answered as "")."""
    item = into.results.add()
    if isinstance(r, ServiceError):
        item.session_id = echoed_id(session_id)
        item.error.code, item.error.message = r.code, r.message
    else:
        item.session_id = session_id
        fill_act_response(item.action, r)


def goal(sel: pb.GoalSelector | None) -> tuple[GoalRef, float | None]:
    """(goal id or name, target) of a GoalSelector; (None, None) when unset."""
    if sel is None:
        return None, None
    kind = sel.WhichOneof("kind")
    if kind == "id":
        return sel.id, None
    if kind == "name":
        return sel.name, None
    if kind == "target":
        return None, sel.target
    return None, None


def observation(req: pb.ActRequest) -> np.ndarray:
    """The observation of an ActRequest as an array.

    Raises:
        InvalidArgument: no observation, or a tensor whose bytes do not match its dtype and shape.
    """
    kind = req.WhichOneof("observation")
    if kind == "values":
        values = req.values.values
        return np.fromiter(values, np.float32, len(values))  # 1.6x faster than np.asarray on a repeated field
    if kind == "tensor":
        t = req.tensor
        return decode_tensor(t.data, t.dtype, t.shape)
    raise InvalidArgument("observation is required: set values or tensor")
