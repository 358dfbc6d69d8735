"""The console's API against real servers: `GET /sessions` (memory and Redis stores), `GET /sessions/{id}/events`
(server-sent events, bounded queues, auth, shutdown) and the static page `GET /ui`."""

from __future__ import annotations

import asyncio
import json
import queue
import threading
import time

import httpx
import pytest
from service_harness import OBS_DIM, RunningServer, make_settings

from gmt.service.activity import TAU_S, Activity
from gmt.service.errors import ResourceExhausted
from gmt.service.events import EventHub

OBS = [0.1] * OBS_DIM
TOKEN = "console-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class EventReader:
    """Reads a session's event stream in a thread; `next(kind)` waits (bounded) for the next event of a kind."""

    def __init__(self, url: str, headers: dict | None = None) -> None:
        self.events: queue.Queue = queue.Queue()
        self.status: int | None = None
        self.headers: httpx.Headers | None = None
        self.ended = threading.Event()
        self._opened = threading.Event()
        self._thread = threading.Thread(target=self._read, args=(url, headers or {}), daemon=True)
        self._thread.start()
        assert self._opened.wait(30), "the event stream did not answer"

    def _read(self, url: str, headers: dict) -> None:
        try:
            with httpx.stream("GET", url, headers=headers, timeout=httpx.Timeout(30, read=60)) as r:
                self.status, self.headers = r.status_code, r.headers
                self._opened.set()
                kind = None
                for line in r.iter_lines():
                    if line.startswith("event: "):
                        kind = line[7:]
                    elif line.startswith("data: "):
                        self.events.put((kind, json.loads(line[6:])))
        finally:
            self._opened.set()
            self.ended.set()

    def next(self, kind: str, timeout: float = 30) -> dict:
        """The data of the next event of `kind` (events of other kinds before it are skipped)."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            assert left > 0, f"no {kind!r} event within {timeout} s"
            try:
                got, data = self.events.get(timeout=left)
            except queue.Empty:
                continue
            if got == kind:
                return data


@pytest.fixture(scope="module")
def served(ckpt_root):
    s = RunningServer(make_settings(checkpoints=[ckpt_root], replica_id="console-1")).start()
    yield s
    s.stop()


@pytest.fixture
def api(served):
    with httpx.Client(base_url=served.url, timeout=30) as c:
        yield c


def _create(api: httpx.Client, goal: int | str = 0) -> str:
    r = api.post("/sessions", json={"model": "tiny-gmt", "goal": goal}, headers=AUTH)
    assert r.status_code == 201, r.text
    return r.json()["session_id"]


def _act(api: httpx.Client, sid: str, n: int = 1) -> None:
    for _ in range(n):
        r = api.post(f"/sessions/{sid}/act", json={"observation": OBS}, headers=AUTH)
        assert r.status_code == 200, r.text


def test_listing_pages_newest_first_with_step_goal_rate_latency_and_replica(api):
    for s in api.get("/sessions", params={"limit": 500}).json()["sessions"]:
        api.delete(f"/sessions/{s['session_id']}")
    sids = [_create(api, goal) for goal in ("low", "medium", "high")]
    _act(api, sids[1], 4)

    doc = api.get("/sessions").json()
    assert doc["total"] == 3 and doc["offset"] == 0 and doc["limit"] == 50 and doc["replica"] == "console-1"
    rows = doc["sessions"]
    assert [r["session_id"] for r in rows] == sids[::-1]  # newest first
    by_id = {r["session_id"]: r for r in rows}
    acted, idle = by_id[sids[1]], by_id[sids[2]]
    assert (acted["model"], acted["goal"], acted["goal_name"], acted["step"]) == ("tiny-gmt", 1, "medium", 4)
    assert acted["acts_per_s"] > 0 and acted["last_latency_ms"] > 0 and acted["served_by"] == "console-1"
    assert (idle["step"], idle["acts_per_s"], idle["last_latency_ms"]) == (0, None, None)
    assert idle["served_by"] == "console-1" and idle["idle_s"] >= 0

    page = api.get("/sessions", params={"offset": 1, "limit": 1}).json()
    assert [r["session_id"] for r in page["sessions"]] == [sids[1]] and page["total"] == 3
    assert api.get("/sessions", params={"offset": 3}).json()["sessions"] == []


@pytest.mark.parametrize(
    "params, field",
    [
        ({"limit": 0}, "limit"),
        ({"limit": 501}, "limit"),
        ({"offset": -1}, "offset"),
        ({"offset": 2**63 - 1}, "offset"),  # past int64 once the page is added: was a 500
        ({"limit": "x"}, "limit"),
    ],
)
def test_listing_refuses_bad_pages(api, params, field):
    r = api.get("/sessions", params=params)
    assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_argument"
    assert field in r.json()["error"]["message"]


def test_listing_is_documented_in_openapi(api):
    doc = api.get("/openapi.json").json()
    op = doc["paths"]["/sessions"]["get"]
    assert {p["name"]: p["schema"].get("maximum") for p in op["parameters"]} == {
        "offset": 10**9,
        "limit": 500,
    }
    assert op["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith("SessionListOut")
    events = doc["paths"]["/sessions/{session_id}/events"]["get"]
    assert "text/event-stream" in events["responses"]["200"]["content"]
    assert {"404", "429"} <= set(events["responses"])


def test_events_follow_acts_goal_changes_resets_and_the_close(served, api):
    sid = _create(api, "low")
    reader = EventReader(f"{served.url}/sessions/{sid}/events")
    assert reader.status == 200 and reader.headers["content-type"].startswith("text/event-stream")
    assert reader.headers["x-session-id"] == sid and reader.headers["cache-control"] == "no-store"
    first = reader.next("session")
    assert (first["session_id"], first["goal"], first["step"]) == (sid, 0, 0)

    _act(api, sid, 2)
    acts = [reader.next("act"), reader.next("act")]
    assert [(a["step"], a["goal"], len(a["action"])) for a in acts] == [(0, 0, 6), (1, 0, 6)]
    assert all(a["latency_ms"] > 0 for a in acts)
    assert api.put(f"/sessions/{sid}/goal", json={"goal": "high"}).status_code == 200
    goal = reader.next("goal")
    assert (goal["goal"], goal["goal_name"], goal["step"], goal["given"]) == (2, "high", 2, {"goal": "high"})
    api.put(f"/sessions/{sid}/goal", json={"target": 1.1, "blend_steps": 3})
    goal = reader.next("goal")
    assert (goal["goal"], goal["given"], goal["blend_steps"]) == (1, {"target": 1.1}, 3)
    assert api.post(f"/sessions/{sid}/reset", json={}).status_code == 200
    assert reader.next("reset") == {"goal": 1, "goal_name": "medium", "step": 0}
    _act(api, sid)
    assert reader.next("act")["step"] == 0

    assert api.delete(f"/sessions/{sid}").status_code == 204
    assert reader.next("closed") == {"session_id": sid}
    assert reader.ended.wait(30), "the stream did not end after the close"


def test_events_see_act_many_items(served, api):
    sid = _create(api)
    reader = EventReader(f"{served.url}/sessions/{sid}/events")
    reader.next("session")
    r = api.post("/act", json={"requests": [{"session_id": sid, "observation": OBS}]})
    assert r.status_code == 200 and "error" not in r.json()["results"][0]
    first = reader.next("act")
    assert first["step"] == 0 and "reward" not in first
    # A reward the client reports with its next act is the previous step's; the page charts it there.
    r = api.post("/act", json={"requests": [{"session_id": sid, "observation": OBS, "reward": 1.5}]})
    assert r.status_code == 200 and "error" not in r.json()["results"][0]
    second = reader.next("act")
    assert (second["step"], second["reward"], second["reward_step"]) == (1, 1.5, 0)
    assert api.post(f"/sessions/{sid}/act", json={"observation": OBS, "reward": -2.0}).status_code == 200
    third = reader.next("act")
    assert (third["step"], third["reward"], third["reward_step"]) == (2, -2.0, 1)
    api.delete(f"/sessions/{sid}")
    assert reader.ended.wait(30)


def test_events_of_an_unknown_session_and_too_many_streams_are_4xx(served, api):
    r = api.get("/sessions/no-such-session/events")
    assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"
    assert "no-such-session" in r.json()["error"]["message"]

    sid = _create(api)
    per_session = served.core.events.per_session
    readers = [EventReader(f"{served.url}/sessions/{sid}/events") for _ in range(per_session)]
    for rd in readers:
        rd.next("session")
    r = api.get(f"/sessions/{sid}/events")
    assert r.status_code == 429 and r.json()["error"]["code"] == "resource_exhausted"
    api.delete(f"/sessions/{sid}")
    assert all(rd.ended.wait(30) for rd in readers)
    assert served.core.events.count == 0  # every subscription was let go


def test_a_reader_that_leaves_is_let_go(served, api):
    sid = _create(api)
    with httpx.stream("GET", f"{served.url}/sessions/{sid}/events", timeout=30) as r:
        assert r.status_code == 200, r.read()
        lines = r.iter_lines()  # held: a dropped generator would close the stream
        assert next(lines) == "event: session"
        assert sid in served.core.events
        metrics = api.get("/metrics").text  # an open stream is not a request in flight
        assert 'gmt_requests_in_flight{transport="rest"} 0.0' in metrics
    deadline = time.monotonic() + 30
    while sid in served.core.events:  # the disconnect ends the subscription, no keep-alive needed
        assert time.monotonic() < deadline, "the subscription outlived its reader"
        time.sleep(0.02)
    api.delete(f"/sessions/{sid}")


def test_hub_queues_are_bounded_and_count_what_they_drop():
    async def run() -> None:
        hub = EventHub(per_session=2, total=3, queue=4)
        assert "s" not in hub
        sub = hub.subscribe("s")
        for i in range(10):
            hub.publish("s", "act", {"step": i})
        events, dropped = sub.take()
        assert [d["step"] for _, d in events] == [6, 7, 8, 9] and dropped == 6
        hub.subscribe("s")
        with pytest.raises(ResourceExhausted):
            hub.subscribe("s")
        hub.subscribe("t")
        with pytest.raises(ResourceExhausted):
            hub.subscribe("u")
        hub.end("s", "closed", {})
        assert sub.closed and sub.take()[0] == [("closed", {})] and "s" not in hub and hub.count == 1
        await asyncio.wait_for(sub.wait(60), 5)  # a closed feed does not wait
        hub.close()
        assert hub.count == 0

    asyncio.run(run())


def test_activity_rate_follows_a_steady_rate_and_decays():
    a = Activity()
    for i in range(200):
        a.record(i * 0.05, 0.001, "r")  # 20 acts/s for 10 s
    assert a.rate(9.95) == pytest.approx(20, rel=0.1)
    assert a.rate(9.95 + 3 * TAU_S) < 0.06 * 20
    assert Activity.load(a.dump()).dump() == a.dump()
    assert Activity.load(None).count == 0 and Activity.load(["x", 1, 2, 3]).count == 0


def test_auth_guards_the_api_but_not_the_page(ckpt_root):
    s = RunningServer(make_settings(checkpoints=[ckpt_root], auth_token=TOKEN)).start()
    try:
        with httpx.Client(base_url=s.url, timeout=30) as c:
            page = c.get("/ui")
            assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
            csp = page.headers["content-security-policy"]
            assert "default-src 'none'" in csp and "connect-src 'self'" in csp
            assert 'src="/ui/console.js"' in page.text
            assert c.get("/ui/console.js").headers["content-type"].startswith("text/javascript")
            assert c.get("/ui/console.css").status_code == 200
            assert c.get("/ui/other.js").status_code == 401  # only the page's own files are open
            missing = c.get("/ui/other.js", headers=AUTH)
            assert missing.status_code == 404 and missing.json()["error"]["code"] == "not_found"

            sid = c.post("/sessions", json={"model": "tiny-gmt", "goal": 0}, headers=AUTH).json()[
                "session_id"
            ]
            for headers, message in (
                ({}, "missing bearer token"),
                ({"Authorization": "Bearer no"}, "invalid"),
            ):
                for path in ("/sessions", f"/sessions/{sid}/events"):
                    r = c.get(path, headers=headers)
                    assert r.status_code == 401 and message in r.json()["error"]["message"], path
            r = c.get(f"/sessions/{sid}/events", params={"token": TOKEN})  # never in a URL
            assert r.status_code == 401
            assert c.get("/sessions", headers=AUTH).json()["total"] == 1
            reader = EventReader(f"{s.url}/sessions/{sid}/events", AUTH)
            assert reader.next("session")["session_id"] == sid
    finally:
        s.stop()
    assert reader.ended.wait(30), "shutdown left the event stream open"


def test_shutdown_ends_open_event_streams_at_once(ckpt_root):
    s = RunningServer(make_settings(checkpoints=[ckpt_root], shutdown_grace_s=30.0)).start()
    with httpx.Client(base_url=s.url, timeout=30) as c:
        sid = c.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
    reader = EventReader(f"{s.url}/sessions/{sid}/events")
    reader.next("session")
    t0 = time.monotonic()
    s.stop()
    assert reader.ended.wait(30)
    assert time.monotonic() - t0 < 10, "shutdown waited for the event stream (grace period 30 s)"


def test_redis_listing_names_the_replica_that_served_each_session(redis_clean, ckpt_root):
    a = RunningServer(
        make_settings(checkpoints=[ckpt_root], redis_url=redis_clean, replica_id="gmt-a")
    ).start()
    b = RunningServer(
        make_settings(checkpoints=[ckpt_root], redis_url=redis_clean, replica_id="gmt-b")
    ).start()
    try:
        with httpx.Client(base_url=a.url, timeout=30) as ca, httpx.Client(base_url=b.url, timeout=30) as cb:
            on_a, on_b, unused = _create(ca, "low"), _create(ca, "medium"), _create(ca, "high")
            _act(ca, on_a, 3)
            _act(cb, on_b, 3)  # b adopts the session from the store
            for client, here in ((ca, "gmt-a"), (cb, "gmt-b")):
                doc = client.get("/sessions").json()
                assert doc["total"] == 3 and doc["replica"] == here
                rows = {r["session_id"]: r for r in doc["sessions"]}
                assert set(rows) == {on_a, on_b, unused}
                assert (rows[on_a]["served_by"], rows[on_a]["step"], rows[on_a]["goal_name"]) == (
                    "gmt-a",
                    3,
                    "low",
                )
                assert (rows[on_b]["served_by"], rows[on_b]["step"], rows[on_b]["goal_name"]) == (
                    "gmt-b",
                    3,
                    "medium",
                )
                assert rows[on_a]["acts_per_s"] > 0 and rows[on_b]["last_latency_ms"] > 0
                assert (rows[unused]["step"], rows[unused]["acts_per_s"], rows[unused]["served_by"]) == (
                    0,
                    None,
                    None,
                )
            assert len(ca.get("/sessions", params={"limit": 2}).json()["sessions"]) == 2
    finally:
        a.stop()
        b.stop()
