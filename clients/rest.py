"""REST client (httpx) for the service's JSON API (DESIGN.md section 6)."""

from __future__ import annotations

import base64
from collections.abc import Sequence
from typing import Any

import httpx
import numpy as np

from clients.base import (
    DEFAULT_BACKOFF_S,
    DEFAULT_RETRIES,
    DEFAULT_TIMEOUT_S,
    ActResult,
    GoalInfo,
    ModelInfo,
    PolicyClient,
    Session,
    SessionInfo,
    as_observation,
    goal_selector,
    with_retries,
)
from clients.errors import DeadlineExceeded, ProtocolError, ServiceError, error_for


def _is_connection_error(e: BaseException) -> bool:
    # Only errors raised before the request was sent: retrying them cannot apply a request twice.
    return isinstance(e, httpx.ConnectError | httpx.ConnectTimeout)


def model_from_json(d: dict) -> ModelInfo:
    """A `ModelInfo` from a `GET /models/{name}` body."""
    return ModelInfo(
        name=d["name"],
        env_id=d["env_id"],
        observation_space=d["observation_space"],
        action_space=d["action_space"],
        context_length=int(d.get("context_length", 0)),
        statistic=d.get("statistic", ""),
        goals=[GoalInfo(**{k: g[k] for k in GoalInfo.__dataclass_fields__}) for g in d.get("goals", [])],
    )


def session_from_json(d: dict) -> SessionInfo:
    """A `SessionInfo` from a session body (fields the server does not send keep their defaults)."""
    fields = {k: d[k] for k in SessionInfo.__dataclass_fields__ if d.get(k) is not None}
    fields["context_goals"] = tuple(fields.get("context_goals", ()))
    return SessionInfo(**fields)


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


class RestClient(PolicyClient):
    """The service over HTTP/JSON.

    Args:
        base_url: e.g. "http://localhost:8000".
        timeout_s: Per-request timeout (connect, read, write).
        retries: Extra attempts when the server cannot be connected to (never after it answered).
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
        if "://" not in base_url:
            base_url = "http://" + base_url
        self.base_url = base_url.rstrip("/")
        self.retries, self.backoff_s = retries, backoff_s
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(
            base_url=self.base_url, timeout=timeout_s, headers=headers, transport=transport
        )

    def _request(self, method: str, path: str, json: dict | None = None) -> Any:
        def send() -> httpx.Response:
            return self._http.request(method, path, json=json)

        try:
            r = with_retries(send, _is_connection_error, self.retries, self.backoff_s, self.base_url)
        except httpx.TimeoutException as e:
            raise DeadlineExceeded(f"{method} {self.base_url}{path} timed out: {e!r}") from e
        except httpx.TransportError as e:
            raise ServiceError(f"{method} {self.base_url}{path} failed: {e!r}", code="transport_error") from e
        if r.is_success:
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
        return [self.get_model(m["name"]) for m in self._request("GET", "/models")["models"]]

    def get_model(self, name: str) -> ModelInfo:
        return model_from_json(self._request("GET", f"/models/{name}"))

    # ----- sessions -----------------------------------------------------------------------------------------
    def create_session(
        self,
        model: str | None = None,
        goal: int | str | None = None,
        *,
        target: float | None = None,
        seed: int | None = None,
        action_mode: str | None = None,
    ) -> Session:
        body: dict[str, Any] = _goal_body(goal, target)
        if model:
            body["model"] = model
        if seed is not None:
            body["seed"] = seed
        if action_mode:
            body["action_mode"] = action_mode
        return Session(self, session_from_json(self._request("POST", "/sessions", body)))

    def get_session(self, session_id: str) -> SessionInfo:
        return session_from_json(self._request("GET", f"/sessions/{session_id}"))

    def act(self, session_id: str, observation: Any) -> ActResult:
        body = {"observation": encode_observation(observation)}
        return act_from_json(self._request("POST", f"/sessions/{session_id}/act", body))

    def act_many(self, items: Sequence[tuple[str, Any]]) -> list[ActResult | ServiceError]:
        body = {"requests": [{"session_id": sid, "observation": encode_observation(o)} for sid, o in items]}
        results = self._request("POST", "/act", body).get("results")
        if not isinstance(results, list) or len(results) != len(items):
            raise ProtocolError(f"POST /act answered {results!r:.200} for {len(items)} requests")
        return [act_item_from_json(d) for d in results]

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
        return session_from_json(self._request("PUT", f"/sessions/{session_id}/goal", body))

    def reset(
        self, session_id: str, goal: int | str | None = None, *, target: float | None = None
    ) -> SessionInfo:
        return session_from_json(
            self._request("POST", f"/sessions/{session_id}/reset", _goal_body(goal, target))
        )

    def close_session(self, session_id: str) -> None:
        self._request("DELETE", f"/sessions/{session_id}")

    def close(self) -> None:
        self._http.close()
