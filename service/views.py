"""What the core answers, whatever the transport: models and versions, sessions, timelines and actions, and the
bounds of its calls. The adapters (REST, gRPC, console) convert these; nothing here knows HTTP or gRPC."""

from __future__ import annotations

from dataclasses import dataclass, field

from gmt.common.spec import ModelInfo, SessionInfo

MAX_ACT_ITEMS = 4096  # most (session, observation) items in one many-session act (POST /act, gRPC ActBatch)
MAX_LIST_SESSIONS = 500  # the longest page of `list_sessions`
MAX_LIST_OFFSET = 10**9  # the largest offset of `list_sessions` (far past any store; larger overflow int64)
MAX_TIMELINE_PAGE = 1000  # the longest page of `timeline` (and its default)
GoalRef = int | str | None


@dataclass(frozen=True)
class VersionView:
    """One loaded version of a model.

    Attributes:
        sessions: Sessions of this version this server holds (all of them with sessions in memory; with a shared
            store, those this replica created or served lately).
        state: `serving` (new sessions may get it) or `draining` (its sessions only; unloaded when none is left).
    """

    version: str
    sessions: int
    state: str
    fingerprint: str


@dataclass(frozen=True)
class ModelView(ModelInfo):
    """What clients learn about a model: the model record (`gmt.common.spec.ModelInfo`) of its default version,
    and its version table."""

    discrete_actions: bool = field(kw_only=True)
    version: str = field(default="", kw_only=True)  # the version this view describes (the default)
    versions: tuple[VersionView, ...] = field(default=(), kw_only=True)
    default_version: str = field(default="", kw_only=True)
    canary: tuple[str, float] | None = field(default=None, kw_only=True)  # (version, share of new sessions)


SessionView = SessionInfo
"""What clients learn about a session: the one session record (`gmt.common.spec.SessionInfo`)."""


@dataclass(frozen=True)
class TimelineView:
    """Every goal a session had (`gmt.service.records`).

    Attributes:
        step: The session's step now (the step of its next act).
        episode: The session's episode now.
        goals: A page of the timeline entries in order: step, episode, goal, given, blend_steps, by, at.
        entries: How many entries there were (more than are kept once the timeline was full).
        offset: The index of the page's first entry.
    """

    session_id: str
    model: str
    model_version: str
    fingerprint: str | None
    step: int
    episode: int
    goals: list[dict]
    entries: int
    offset: int = 0


@dataclass(frozen=True)
class ActResult:
    """One action: `action` for Box spaces, `discrete_action` for Discrete ones; `step` is the observation's."""

    session_id: str
    action: list[float] | None
    discrete_action: int | None
    step: int
    goal: int
