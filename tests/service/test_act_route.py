"""`POST /sessions/{id}/act` and `POST /act` have one implementation each (`gmt.service.rest.act.answer`,
`answer_many`): the documented routes, reached when the fast path `FastAct` is taken out of the stack, answer every
case as the fast path does."""

from __future__ import annotations

import json

import numpy as np
from service_harness import OBS_DIM, make_settings
from starlette.testclient import TestClient

from gmt.service.rest import app as app_module

SID = "route-twin"


def _answers(ckpt_root, monkeypatch, fast: bool) -> list[tuple[int, dict, str | None]]:
    """(status, JSON body, X-Session-Id) of the same act requests on a fresh app, with or without `FastAct`."""
    if not fast:
        monkeypatch.setattr(
            app_module, "FastAct", lambda app, settings: app
        )  # only the documented route is left
    obs = np.random.default_rng(3).normal(size=OBS_DIM).astype(np.float32).tolist()
    requests = [
        (SID, json.dumps({"observation": obs, "step": 0}), "application/json"),  # answered
        (SID, json.dumps({"observation": obs, "step": 0}), "application/json"),  # a retry: the same answer
        (SID, json.dumps({"observation": obs, "step": 5}), "application/json"),  # 409: not the session's step
        (SID, json.dumps({"observation": obs[:3]}), "application/json"),  # 400: wrong size
        (SID, '{"observation": [1, 2', "application/json"),  # 400: broken JSON
        (SID, json.dumps({"observation": "x"}), "application/json"),  # 400: not a list
        (SID, json.dumps({"observation": obs}), "text/plain"),  # 415
        ("no-such-session", json.dumps({"observation": obs}), "application/json"),  # 404
        (SID, "", "application/json"),  # 400: no body
    ]
    many = [  # POST /act
        (json.dumps({"requests": [{"session_id": SID, "observation": obs, "step": 1}]}), "application/json"),
        (
            json.dumps(  # mixed: an answer, a wrong size, an unknown session, a repeat
                {
                    "requests": [
                        {"session_id": SID, "observation": obs},
                        {"session_id": "twin-2", "observation": obs[:2]},
                        {"session_id": "no-such-session", "observation": obs},
                        {"session_id": SID, "observation": obs},
                    ]
                }
            ),
            "application/json",
        ),
        ('{"requests": [', "application/json"),  # 400: broken JSON
        ("null", "application/json"),  # 400: not an object
        ("", "application/json"),  # 400: no body
        (json.dumps({"requests": []}), "text/plain"),  # 415
        (
            json.dumps({"requests": [{"session_id": SID, "observation": [0]}] * 4097}),
            "application/json",
        ),  # 400
    ]
    settings = make_settings(checkpoints=[ckpt_root], max_request_bytes=512 * 1024)
    out = []
    with TestClient(app_module.create_app(settings)) as c:
        created = c.post("/sessions", json={"model": "tiny-gmt", "session_id": SID, "seed": 1, "goal": 1})
        assert created.status_code == 201, created.text
        assert (
            c.post("/sessions", json={"model": "tiny-gmt", "session_id": "twin-2", "goal": 0}).status_code
            == 201
        )
        for sid, body, content_type in requests:
            r = c.post(f"/sessions/{sid}/act", content=body, headers={"content-type": content_type})
            out.append((r.status_code, r.json(), r.headers.get("x-session-id")))
        for body, content_type in many:
            r = c.post("/act", content=body, headers={"content-type": content_type})
            out.append((r.status_code, r.json(), r.headers.get("x-session-id")))
    monkeypatch.undo()
    return out


def test_the_documented_route_answers_as_the_fast_path(ckpt_root, monkeypatch) -> None:
    fast = _answers(ckpt_root, monkeypatch, fast=True)
    route = _answers(ckpt_root, monkeypatch, fast=False)
    assert [s for s, _, _ in fast] == [200, 200, 409, 400, 400, 400, 415, 404, 400] + [
        200,
        200,
        400,
        400,
        400,
        415,
        400,
    ]
    assert fast[0] == fast[1] and fast[0][2] == SID
    mixed = fast[10][1]["results"]
    assert "action" in mixed[0] and [r["error"]["code"] for r in mixed[1:]] == [
        "invalid_argument",
        "not_found",
        "invalid_argument",
    ], mixed
    assert route == fast
