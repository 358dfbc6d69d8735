"""The one client interface both transports implement, the values it returns, and the Session handle.

`PolicyClient` is what the runner and users code against; `gmt.client.rest.RestClient` and
`gmt.client.grpc.GrpcClient` implement it.

Retries (a few, with exponential backoff) never apply anything twice:
- a call that never reached a server (refused connection) is always retried;
- an answer saying nothing was applied and another attempt may succeed (`aborted`: another replica changed the
  session meanwhile; `unavailable` answered by a replica: shutting down, store unreachable) is always retried;
- a call that may or may not have been applied (the connection broke, a proxy answered 502, a gRPC stream was
  reset: typically the replica died) is retried only when repeating it is harmless: reads, reset, close,
  set_goal without a blend, and acts that carry the step they are for. The client tracks each session's next
  step (0 after create or reset) and sends it with every act, so a repeated act is answered again by the
  server instead of stepping twice. Creating a session, acting on a session whose step this client does not
  know, and a blended set_goal are not retried after such a failure.
Every other answer (invalid argument, not found, ...) is final.
"""

from __future__ import annotations

import abc
import dataclasses
import math
import re
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from gmt.client.errors import ConnectionFailed, NotFound, ServiceError
from gmt.common.spec import GoalInfo as GoalInfo  # part of the client interface, as ModelInfo
from gmt.common.spec import ModelInfo
from gmt.common.spec import SessionInfo as SessionInfo  # the one session record

T = TypeVar("T")

DEFAULT_TIMEOUT_S = 10.0
DEFAULT_RETRIES = 3
DEFAULT_BACKOFF_S = 0.2


@dataclass(frozen=True)
class TimelineEntry:
    """One goal a session had, from `step` (of `episode`) on; `given` is how it was asked for, `by` who asked
    (create, reset, rest, grpc or stream), `at` the server's clock."""

    step: int
    episode: int
    goal: int
    given: dict
    blend_steps: int
    by: str
    at: float


@dataclass(frozen=True)
class Timeline:
    """Every goal a session had (`GET /sessions/{id}/timeline`, gRPC `GetTimeline`)."""

    session_id: str
    model: str
    fingerprint: str | None
    step: int
    episode: int
    entries: int
    goals: list[TimelineEntry] = field(default_factory=list)


TIMELINE_PAGE = 1000  # timeline entries a server answers per read at most


def whole_timeline(page: Callable[[int], Timeline]) -> Timeline:
    """Every entry of a timeline the server answers a page at a time: `page(offset)` until a short page."""
    first = page(0)
    goals = list(first.goals)
    while len(goals) < first.entries:
        more = page(len(goals)).goals
        if not more:  # past the entries a server keeps (the timeline is full)
            break
        goals += more
    return dataclasses.replace(first, goals=goals)


_INFO_KEY = re.compile(r"[A-Za-z0-9_.:/-]{1,64}")  # what the server accepts as an info key


def report_info(info: Mapping[str, Any] | None, limit: int = 32) -> dict[str, float]:
    """The part of an environment's `info` a server accepts with an act: finite scalar numbers (at most
    `limit`) under keys of 1 to 64 letters, digits, '_', '.', ':', '/' or '-'; anything else is left out."""
    out: dict[str, float] = {}
    for k, v in (info or {}).items():
        if len(out) >= limit:
            break
        if isinstance(v, bool) or not isinstance(k, str) or not _INFO_KEY.fullmatch(k):
            continue
        if isinstance(v, int | float | np.integer | np.floating) or (
            isinstance(v, np.ndarray) and v.ndim == 0
        ):
            x = float(v)
            if math.isfinite(x) and abs(x) <= 1e12:
                out[k] = x
    return out


def report_fields(
    reward: float | None = None,
    terminated: bool | None = None,
    truncated: bool | None = None,
    info: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """The report on the previous action as the fields an act carries (those given only)."""
    out: dict[str, Any] = {}
    if reward is not None:
        out["reward"] = float(reward)
    if terminated is not None:
        out["terminated"] = bool(terminated)
    if truncated is not None:
        out["truncated"] = bool(truncated)
    if info:
        out["info"] = {k: float(v) for k, v in info.items()}
    return out


@dataclass(frozen=True)
class ActResult:
    """The answer to one observation.

    Attributes:
        action: Float32 array for continuous actions, int for discrete ones.
        step: Timestep of the observation just answered (0 for the first of an episode).
        goal: The goal the session pursued for this action (changes made by anyone show up here).
    """

    action: np.ndarray | int
    step: int
    goal: int


def batch_routing_key(session_ids: Sequence[str]) -> str:
    """The routing key of a many-session call (`X-Session-Id` / `x-session-id`): the same for the same sessions
    whatever their order, so a proxy that hashes on it sends every tick of a game server to one replica, which
    then holds those sessions and acts without reading the shared store."""
    return min(session_ids)


def new_session_id() -> str:
    """A fresh session id drawn by the client (what makes a retried create safe)."""
    return uuid.uuid4().hex


def goal_selector(goal: int | str | None = None, target: float | None = None) -> tuple[str, Any] | None:
    """("id", int), ("name", str), ("target", float), or None when neither is given.

    Raises:
        ValueError: both given, or a goal that is neither int nor str.
    """
    if goal is not None and target is not None:
        raise ValueError("give either a goal (id or name) or a target value, not both")
    if target is not None:
        return "target", float(target)
    if goal is None:
        return None
    if isinstance(goal, bool) or not isinstance(goal, int | np.integer | str):
        raise ValueError(f"goal must be an id (int) or a name (str), got {goal!r}")
    return ("name", goal) if isinstance(goal, str) else ("id", int(goal))


def as_observation(obs: Any) -> np.ndarray:
    """The observation as a NumPy array; floats become float32 (what the model and gRPC use), images stay."""
    x = np.asarray(obs)
    if not np.issubdtype(x.dtype, np.floating):
        return x
    with np.errstate(over="ignore"):  # beyond float32: infinite, which the server refuses by name
        return x.astype(np.float32)


def _reason(e: BaseException) -> str:
    """Why a connection failed, on one line: a gRPC error's details (its str() is a multi-line dump)."""
    details = getattr(e, "details", None)
    text = details() if callable(details) else str(e)
    return " ".join(str(text or type(e).__name__).split())


def with_retries(
    call: Callable[[], T],
    is_connection_error: Callable[[BaseException], bool],
    retries: int,
    backoff_s: float,
    where: str,
    is_retryable: Callable[[BaseException], bool] | None = None,
) -> T:
    """Run `call`, retrying up to `retries` times (exponential backoff) when it fails to connect, or when
    `is_retryable(error)` says another attempt is safe.

    Raises:
        ConnectionFailed: the last attempt failed to connect.
        Exception: the last attempt's own error otherwise.
    """
    for attempt in range(retries + 1):
        try:
            return call()
        except Exception as e:
            connect = is_connection_error(e)
            if not connect and not (is_retryable is not None and is_retryable(e)):
                raise
            if attempt == retries:
                if connect:
                    raise ConnectionFailed(
                        f"could not connect to {where} after {attempt + 1} attempt(s): {_reason(e)}"
                    ) from e
                raise
            time.sleep(backoff_s * 2**attempt)
    raise AssertionError("unreachable")


# Error codes that prove a call was not applied: the session's step did not move.
_NOT_APPLIED = frozenset(
    {
        "invalid_argument",
        "unauthenticated",
        "permission_denied",
        "not_found",
        "failed_precondition",
        "aborted",
        "resource_exhausted",
        "payload_too_large",
    }
)


class Session:
    """A handle on one server session; a context manager that closes the session on exit.

    Attributes:
        info: The session's state as of its creation or last set_goal / reset.
    """

    def __init__(self, client: PolicyClient, info: SessionInfo) -> None:
        self._client = client
        self.info = info
        self.closed = False

    @property
    def id(self) -> str:
        """The session id."""
        return self.info.session_id

    @property
    def session_id(self) -> str:
        """The session id (`id`, spelled as the server's answers spell it)."""
        return self.info.session_id

    def act(self, observation: Any, **report: Any) -> ActResult:
        """Send one observation; get the action, the step and the goal it was chosen for.

        Args:
            observation: What the environment returned.
            **report: The outcome of the previous action (`reward`, `terminated`, `truncated`, `info`), which a
                recorded session keeps.
        """
        return self._client.act(self.id, observation, **report)

    def set_goal(
        self, goal: int | str | None = None, *, target: float | None = None, blend_steps: int = 0
    ) -> SessionInfo:
        """Change the goal (id, name, or nearest to `target`) from the next step on, optionally blended."""
        self.info = self._client.set_goal(self.id, goal, target=target, blend_steps=blend_steps)
        return self.info

    def reset(self, goal: int | str | None = None, *, target: float | None = None) -> SessionInfo:
        """Start a new episode, keeping the goal unless one is given."""
        self.info = self._client.reset(self.id, goal, target=target)
        return self.info

    def timeline(self) -> Timeline:
        """Every goal the session had."""
        return self._client.get_timeline(self.id)

    def refresh(self) -> SessionInfo:
        """Fetch the session's current state from the server."""
        self.info = self._client.get_session(self.id)
        return self.info

    def close(self) -> None:
        """Close the session on the server (once)."""
        if not self.closed:
            self.closed = True
            self._client.close_session(self.id)

    def __enter__(self) -> Session:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            self.close()
        except NotFound:
            pass  # already gone (expired, or closed elsewhere): what closing was for
        except Exception:
            if exc_type is None:
                raise  # closing failed on its own: say so; otherwise keep the original error


class PolicyClient(abc.ABC):
    """The controllable-policy service, whichever transport carries it. Use as a context manager.

    The client remembers the next step of every session it created, reset, read or acted on, and sends it with
    each act (see the module docstring). If something else steps the same session meanwhile, the next act
    fails with `failed_precondition` naming the session's step; `get_session` brings the client up to date.
    """

    # ----- the expected step of each session --------------------------------------------------------------
    @property
    def _next_steps(self) -> dict[str, int]:
        steps = self.__dict__.get("_steps")
        if steps is None:
            steps = self.__dict__["_steps"] = {}
        return steps

    def expected_step(self, session_id: str) -> int | None:
        """The step the next act of this session is for, as this client knows it (None: unknown)."""
        return self._next_steps.get(session_id)

    def _seen_session(self, info: SessionInfo) -> SessionInfo:
        self._next_steps[info.session_id] = int(info.step)
        return info

    def _seen_act(self, session_id: str, result: ActResult | Exception) -> None:
        if isinstance(result, ActResult):
            self._next_steps[session_id] = result.step + 1
        elif getattr(result, "code", None) not in _NOT_APPLIED:
            self._next_steps.pop(session_id, None)  # it may have stepped: unknown until the next answer

    def _forget(self, session_id: str) -> None:
        self._next_steps.pop(session_id, None)

    @abc.abstractmethod
    def list_models(self) -> list[ModelInfo]:
        """Every model the server serves."""

    @abc.abstractmethod
    def get_model(self, name: str) -> ModelInfo:
        """One model's spec: spaces, goal table, context length."""

    @abc.abstractmethod
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
        """Open a session on `model` (None: the server's only model) pursuing a goal (id, name or target).

        The client names the session (`session_id`, default a fresh random id), so that a create whose answer
        was lost is retried safely: the server answers the session the first attempt created. `record` asks the
        server to record the episode (None: as its --record-share draws it).
        """

    @abc.abstractmethod
    def get_session(self, session_id: str) -> SessionInfo:
        """A session's current state."""

    @abc.abstractmethod
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
        """One step: observation in, action out; optionally the outcome of the previous action (reward,
        terminated, truncated, info: `report_info` picks what a server accepts), which a recorded session
        keeps."""

    @abc.abstractmethod
    def get_timeline(self, session_id: str) -> Timeline:
        """Every goal a session had (read a page of at most `TIMELINE_PAGE` entries at a time)."""

    @abc.abstractmethod
    def act_many(self, items: Sequence[tuple]) -> list[ActResult | ServiceError]:
        """One step for each of many sessions in one call (one forward pass on the server).

        Args:
            items: (session id, observation) pairs, or (session id, observation, report) with the report a dict
                of `reward`, `terminated`, `truncated`, `info`; a session may appear once per call.

        Returns:
            One entry per item, in order: the `ActResult` that `act` would return, or, for an item that failed
            alone (bad observation, unknown or repeated session), the `ServiceError` subclass instance that `act`
            would have raised (returned, not raised; that session is unchanged).

        Raises:
            ServiceError: the whole call failed (e.g. too many items, bad token, server unreachable).
        """

    @abc.abstractmethod
    def set_goal(
        self,
        session_id: str,
        goal: int | str | None = None,
        *,
        target: float | None = None,
        blend_steps: int = 0,
    ) -> SessionInfo:
        """Change a session's goal from its next step on."""

    @abc.abstractmethod
    def reset(
        self, session_id: str, goal: int | str | None = None, *, target: float | None = None
    ) -> SessionInfo:
        """Start a new episode in a session (keeping its goal unless one is given)."""

    @abc.abstractmethod
    def close_session(self, session_id: str) -> None:
        """Close a session."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the connection."""

    def __enter__(self) -> PolicyClient:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()
