"""REST client (httpx) for the service's JSON API (docs/architecture.md, "API shapes")."""

from __future__ import annotations

import base64
import json as jsonlib
from collections.abc import Mapping, Sequence
from typing import Any

import httpx
import numpy as np

from gmt.client.base import (
    DEFAULT_BACKOFF_S,
    DEFAULT_RETRIES,
    DEFAULT_TIMEOUT_S,
    TIMELINE_PAGE,
    ActResult,
    PolicyClient,
    Session,
    SessionInfo,
    Timeline,
    TimelineEntry,
    as_observation,
    batch_routing_key,
    goal_selector,
    new_session_id,
    report_fields,
    whole_timeline,
    with_retries,
)
from gmt.client.errors import (
    DeadlineExceeded,
    InvalidArgument,
    ProtocolError,
    ServiceError,
    Unavailable,
    error_for,
)
from gmt.common.spec import GoalInfo, ModelInfo


def _is_connection_error(e: BaseException) -> bool:
    # Only errors raised before the request was sent: retrying them cannot apply a request twice.
    return isinstance(e, httpx.ConnectError | httpx.ConnectTimeout)


# The request was sent (it may have been applied) and the connection broke before the answer.
_BROKEN = (httpx.ReadError, httpx.WriteError, httpx.RemoteProtocolError)


class _RetryableAnswer(Exception):
    """An answer worth another attempt (see `_worth_retrying`), carried out of `with_retries`."""

    def __init__(self, response: httpx.Response) -> None:
        super().__init__(f"HTTP {response.status_code}")
        self.response = response


def _error_code(r: httpx.Response) -> str:
    try:
        err = r.json().get("error")
    except (ValueError, AttributeError):
        return ""
    return str(err.get("code", "")) if isinstance(err, dict) else ""


def _worth_retrying(r: httpx.Response, safe: bool) -> bool:
    """409 `aborted` and a replica's 503 `unavailable` applied nothing; a proxy's 502 (or a 503 without the
    service's error body) may hide a replica that applied the request and died: only a `safe` call is repeated."""
    if r.status_code == 409:
        return _error_code(r) == "aborted"
    if r.status_code == 503:
        return safe or _error_code(r) == "unavailable"
    return r.status_code == 502 and safe


def model_from_json(d: dict) -> ModelInfo:
    """A `ModelInfo` from a `GET /models/{name}` body."""
    fields = {k: d[k] for k in ModelInfo.__dataclass_fields__ if d.get(k) is not None}
    fields["goals"] = [
        GoalInfo(**{k: g[k] for k in GoalInfo.__dataclass_fields__}) for g in fields.get("goals", [])
    ]
    fields["action_modes"] = list(fields.get("action_modes", []))
    return ModelInfo(**fields)


def session_from_json(d: dict) -> SessionInfo:
    """A `SessionInfo` from a session body (fields the server does not send keep their defaults)."""
    fields = {k: d[k] for k in SessionInfo.__dataclass_fields__ if d.get(k) is not None}
    fields["context_goals"] = tuple(fields.get("context_goals", ()))
    return SessionInfo(**fields)


def timeline_from_json(d: dict) -> Timeline:
    """A `Timeline` from a `GET /sessions/{id}/timeline` body."""
    fields = TimelineEntry.__dataclass_fields__
    return Timeline(
        session_id=d["session_id"],
        model=d["model"],
        fingerprint=d.get("fingerprint"),
        step=int(d["step"]),
        episode=int(d.get("episode", 0)),
        entries=int(d.get("entries", len(d["goals"]))),
        goals=[TimelineEntry(**{k: e[k] for k in fields}) for e in d["goals"]],
    )


def act_from_json(d: dict) -> ActResult:
    """An `ActResult` from a `POST /sessions/{id}/act` body."""
    a = d["action"]
    action = np.asarray(a, dtype=np.float32) if isinstance(a, list) else int(a)
    return ActResult(action=action, step=int(d["step"]), goal=int(d["goal"]))


def act_item_from_json(d: dict) -> ActResult | ServiceError:
    """One item of a `POST /act` answer: an `ActResult`, or the `ServiceError` that failed the item."""
    err = d.get("error")
    if isinstance(err, dict):
        return error_for(str(err.get("code", "")), str(err.get("message", "")))
    return act_from_json(d)


def encode_observation(obs: Any) -> list | dict:
    """Float observations as nested lists of float32 values; other dtypes (images) as base64 raw arrays."""
    x = as_observation(obs)
    if x.dtype == np.float32:
        return x.tolist()
    x = np.ascontiguousarray(x)
    return {"data": base64.b64encode(x.tobytes()).decode(), "dtype": str(x.dtype), "shape": list(x.shape)}


def _goal_body(goal: int | str | None, target: float | None) -> dict:
    sel = goal_selector(goal, target)
    if sel is None:
        return {}
    kind, value = sel
    return {"target": value} if kind == "target" else {"goal": value}


def rest_base_url(server: str) -> str:
    """A server's REST base URL as the clients take it: `http://` is added to a bare `host:port`."""
    return (server if "://" in server else "http://" + server).rstrip("/")


class RestClient(PolicyClient):
    """The service over HTTP/JSON.

    Args:
        base_url: e.g. "http://localhost:8000".
        timeout_s: Per-request timeout (connect, read, write).
        retries: Extra attempts after a failure that a retry cannot make worse (see `gmt.client.base`).
        backoff_s: First retry delay; doubles with each retry.
        token: Bearer token, when the server requires one.
        transport: An httpx transport to use instead of the network (tests).
    """

    def __init__(
        self,
        base_url: str = "http://localhost:8000",
        timeout_s: float = DEFAULT_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        backoff_s: float = DEFAULT_BACKOFF_S,
        token: str | None = None,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.base_url = rest_base_url(base_url)
        self.retries, self.backoff_s = retries, backoff_s
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(
            base_url=self.base_url, timeout=timeout_s, headers=headers, transport=transport
        )

    def _request(
        self,
        method: str,
        path: str,
        json: dict | None = None,
        *,
        safe: bool = False,
        gone_ok_on_retry: bool = False,
        headers: dict[str, str] | None = None,
        raw: bool = False,
    ) -> Any:
        """Send one request and decode its answer.

        Args:
            safe: Applying the request twice is the same as once (reads, reset, close, acts with a step):
                it may be repeated after a failure that leaves unknown whether it was applied.
            gone_ok_on_retry: A 404 after an attempt that may have been applied is success (it deleted it).
            raw: Return a successful answer's bytes instead of decoding JSON.

        Raises:
            InvalidArgument: the body holds NaN or an infinity, which JSON cannot carry (nothing is sent).
            ServiceError: the server's answer, or the failure to get one (a subclass per code).
        """
        maybe_applied = False  # an earlier attempt may have been applied
        content = None
        if json is not None:  # encoded once for every attempt, as httpx's json= would each time
            try:
                content = jsonlib.dumps(
                    json, ensure_ascii=False, separators=(",", ":"), allow_nan=False
                ).encode()
            except ValueError:  # only NaN and infinities fail here: JSON has no spelling for them
                raise InvalidArgument(
                    f"{method} {path}: the body holds NaN or an infinity, which JSON cannot carry (the server "
                    "refuses non-finite values too)",
                    code="invalid_argument",
                ) from None
            headers = {**(headers or {}), "Content-Type": "application/json"}

        def send() -> httpx.Response:
            r = self._http.request(method, path, content=content, headers=headers)
            if _worth_retrying(r, safe):
                raise _RetryableAnswer(r)
            return r

        def retryable(e: BaseException) -> bool:
            nonlocal maybe_applied
            if isinstance(e, _RetryableAnswer):
                r = e.response
                maybe_applied |= r.status_code == 502 or _error_code(r) not in ("aborted", "unavailable")
                return True
            if safe and isinstance(e, _BROKEN):
                maybe_applied = True
                return True
            return False

        try:
            r = with_retries(
                send, _is_connection_error, self.retries, self.backoff_s, self.base_url, retryable
            )
        except _RetryableAnswer as e:
            r = e.response
        except httpx.TimeoutException as e:
            raise DeadlineExceeded(f"{method} {self.base_url}{path} timed out: {e!r}") from e
        except httpx.TransportError as e:  # sent, then the connection broke: as gRPC reports it
            if isinstance(e, httpx.RemoteProtocolError) and "illegal" in str(e):  # not HTTP/1.x: a gRPC port
                raise ProtocolError(
                    f"{method} {self.base_url}{path}: the answer is not HTTP/1.1 ({e}): {self.base_url} looks like a "
                    "gRPC port; this REST client needs the server's REST port (gmt serve --rest-port, default 8000), "
                    "or use GrpcClient (gmt run --grpc HOST:PORT) for this one. The request was not applied"
                ) from e
            raise Unavailable(
                f"{method} {self.base_url}{path}: the connection broke before the answer ({e!r}); the request may "
                "have been applied",
                code="unavailable",
            ) from e
        if r.status_code == 404 and gone_ok_on_retry and maybe_applied:
            return None
        if r.is_success:
            if raw:
                return r.content
            if r.status_code == 204 or not r.content:
                return None
            try:
                return r.json()
            except ValueError as e:
                raise ProtocolError(f"{method} {path}: answer is not JSON: {r.text[:200]!r}") from e
        raise self._error(r)

    @staticmethod
    def _error(r: httpx.Response) -> ServiceError:
        try:
            body = r.json()
        except ValueError:
            body = None
        if isinstance(body, dict) and isinstance(body.get("error"), dict):
            err = body["error"]
            return error_for(str(err.get("code", "")), str(err.get("message", "")), r.status_code)
        detail = body.get("detail") if isinstance(body, dict) else None
        message = str(detail) if detail is not None else (r.text.strip() or r.reason_phrase)
        return error_for("", message, r.status_code)

    # ----- models -------------------------------------------------------------------------------------------
    def list_models(self) -> list[ModelInfo]:
        # GET /models answers summaries; each model's spaces and goal table come from GET /models/{name}.
        return [self.get_model(m["name"]) for m in self._request("GET", "/models", safe=True)["models"]]

    def get_model(self, name: str) -> ModelInfo:
        return model_from_json(self._request("GET", f"/models/{name}", safe=True))

    # ----- sessions -----------------------------------------------------------------------------------------
    def create_session(
        self,
        model: str | None = None,
        goal: int | str | None = None,
        *,
        target: float | None = None,
        seed: int | None = None,
        action_mode: str | None = None,
        session_id: str | None = None,
        record: bool | None = None,
    ) -> Session:
        body: dict[str, Any] = _goal_body(goal, target)
        if model:
            body["model"] = model
        if seed is not None:
            body["seed"] = seed
        if action_mode:
            body["action_mode"] = action_mode
        if record is not None:
            body["record"] = record
        body["session_id"] = session_id or new_session_id()
        info = self._seen_session(session_from_json(self._request("POST", "/sessions", body, safe=True)))
        return Session(self, info)

    def get_session(self, session_id: str) -> SessionInfo:
        return self._seen_session(
            session_from_json(self._request("GET", f"/sessions/{session_id}", safe=True))
        )

    def act(
        self,
        session_id: str,
        observation: Any,
        *,
        reward: float | None = None,
        terminated: bool | None = None,
        truncated: bool | None = None,
        info: Mapping[str, float] | None = None,
    ) -> ActResult:
        body: dict[str, Any] = {"observation": encode_observation(observation)}
        body |= report_fields(reward, terminated, truncated, info)
        step = self.expected_step(session_id)
        if step is not None:
            body["step"] = step
        try:
            result = act_from_json(
                self._request("POST", f"/sessions/{session_id}/act", body, safe=step is not None)
            )
        except ServiceError as e:
            self._seen_act(session_id, e)
            raise
        self._seen_act(session_id, result)
        return result

    def act_many(self, items: Sequence[tuple]) -> list[ActResult | ServiceError]:
        requests = []
        for sid, o, *report in items:
            requests.append({"session_id": sid, "observation": encode_observation(o)})
            requests[-1] |= report_fields(**report[0]) if report and report[0] else {}
            if (step := self.expected_step(sid)) is not None:
                requests[-1]["step"] = step
        safe = all("step" in r for r in requests)
        try:
            # Routed as one session would be (the same key every tick for the same sessions): behind a proxy that
            # hashes on the session id, a game server's calls keep landing on the replica that holds its sessions.
            key = {"X-Session-Id": batch_routing_key([sid for sid, *_ in items])} if items else None
            results = self._request("POST", "/act", {"requests": requests}, safe=safe, headers=key).get(
                "results"
            )
        except ServiceError as e:
            for sid, *_ in items:
                self._seen_act(sid, e)
            raise
        if not isinstance(results, list) or len(results) != len(items):
            raise ProtocolError(f"POST /act answered {results!r:.200} for {len(items)} requests")
        out = [act_item_from_json(d) for d in results]
        for (sid, *_), r in zip(items, out, strict=True):
            self._seen_act(sid, r)
        return out

    def set_goal(
        self,
        session_id: str,
        goal: int | str | None = None,
        *,
        target: float | None = None,
        blend_steps: int = 0,
    ) -> SessionInfo:
        body = _goal_body(goal, target)
        if not body:
            raise ValueError("set_goal needs a goal (id or name) or a target")
        if blend_steps:
            body["blend_steps"] = blend_steps
        # Setting a goal again is harmless, unless a blend would restart.
        answer = self._request("PUT", f"/sessions/{session_id}/goal", body, safe=not blend_steps)
        return self._seen_session(session_from_json(answer))

    def reset(
        self, session_id: str, goal: int | str | None = None, *, target: float | None = None
    ) -> SessionInfo:
        answer = self._request("POST", f"/sessions/{session_id}/reset", _goal_body(goal, target), safe=True)
        return self._seen_session(session_from_json(answer))

    def get_timeline(self, session_id: str) -> Timeline:
        path = f"/sessions/{session_id}/timeline?limit={TIMELINE_PAGE}&offset="
        return whole_timeline(
            lambda offset: timeline_from_json(self._request("GET", f"{path}{offset}", safe=True))
        )

    def get_recording(self, session_id: str):
        """The session's recording so far, as a `gmt.common.recording.Recording` (fetched as npz)."""
        from gmt.common.recording import Recording

        data = self._request("GET", f"/sessions/{session_id}/recording?format=npz", safe=True, raw=True)
        return Recording.from_npz(data)

    def close_session(self, session_id: str) -> None:
        self._forget(session_id)
        # A repeated DELETE answering 404 means an earlier attempt closed it.
        self._request("DELETE", f"/sessions/{session_id}", safe=True, gone_ok_on_retry=True)

    def close(self) -> None:
        self._http.close()
