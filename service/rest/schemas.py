"""JSON bodies of the REST API (pydantic v2), as docs/architecture.md ("API shapes") lists them.

Request bodies are validated strictly: a number is never read from a string or a boolean, so that the server
accepts exactly what its OpenAPI schema (`gmt.service.rest.openapi`) admits. Integers may be written as integral
JSON numbers (`2.0`), which JSON Schema counts as integers too.
"""

from __future__ import annotations

import typing
from dataclasses import MISSING, asdict, fields
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    StrictBool,
    StrictInt,
    StrictStr,
    create_model,
    field_validator,
)

from gmt.common.spec import GoalInfo, ModelInfo, SessionInfo
from gmt.model.checkpoint import VERSION_PATTERN
from gmt.model.engine import MAX_BLEND_STEPS
from gmt.service.examples import Example
from gmt.service.records import MAX_INFO_KEYS, MAX_REPORTED
from gmt.service.views import MAX_ACT_ITEMS, ModelView, SessionView, TimelineView


def _integral(v: object) -> object:
    return int(v) if isinstance(v, float) and v.is_integer() else v


JsonInt = Annotated[StrictInt, BeforeValidator(_integral)]
"""An integer: a JSON integer or an integral JSON number (`3.0`); never a string or a boolean."""
GoalRef = JsonInt | StrictStr


class _Request(BaseModel):
    """A request body: strict types (unknown fields are ignored)."""

    model_config = ConfigDict(strict=True)


class Space(BaseModel):
    """A Gymnasium Box or Discrete space; infinite bounds are null."""

    type: Literal["box", "discrete"]
    shape: list[int]
    dtype: str
    low: list[float | None] | None = None
    high: list[float | None] | None = None
    n: int | None = None


def record_schema(
    record: type,
    exclude: frozenset[str] = frozenset(),
    types: dict[str, object] | None = None,
    base: type[BaseModel] = BaseModel,
) -> type[BaseModel]:
    """A pydantic model of a record dataclass (`gmt.common.spec`): the same fields, types (a nested record's
    `types` gives its schema) and descriptions; a field the record marks `optional` keeps its default, every
    other one is required (an answer always carries it)."""

    def wire(t: object) -> object:  # a tuple of one type is a JSON array: list it as one
        args = typing.get_args(t)
        return list[args[0]] if typing.get_origin(t) is tuple and args[1:] == (Ellipsis,) else t

    hints = typing.get_type_hints(record)
    spec = {}
    for f in fields(record):
        if f.name in exclude:
            continue
        default = f.default if f.metadata.get("optional") and f.default is not MISSING else ...
        kind = (types or {}).get(f.name, wire(hints[f.name]))
        spec[f.name] = (kind, Field(default, description=f.metadata.get("doc") or None))
    return create_model(f"_{record.__name__}Record", __base__=base, **spec)


class GoalOut(record_schema(GoalInfo)):
    """One goal of a model's goal table (a cluster of the per-trajectory statistic)."""


class VersionOut(BaseModel):
    """One loaded version of a model."""

    version: str = Field(
        description="gmt.json's `version`, else the checkpoint fingerprint's first 12 hex digits."
    )
    sessions: int = Field(description="Sessions of this version the answering server holds.")
    state: Literal["serving", "draining"] = Field(
        description="`serving`: new sessions may get it; `draining`: its sessions only, unloaded once none is left."
    )
    fingerprint: str = Field(description="sha256 hex of the checkpoint's weights and metadata.")


class CanaryOut(BaseModel):
    """A version that gets `share` of the new sessions that name no version (by a hash of the session id)."""

    version: str
    share: float


class _Versions(BaseModel):
    """A model's version table."""

    versions: list[VersionOut] = Field(default_factory=list)
    default_version: str = Field("", description="The version new sessions get unless they name one.")
    canary: CanaryOut | None = Field(None, description="Set while a canary runs.")


def _versions(v: ModelView) -> dict:
    return {
        "versions": [VersionOut(**asdict(x)) for x in v.versions],
        "default_version": v.default_version,
        "canary": None if v.canary is None else CanaryOut(version=v.canary[0], share=v.canary[1]),
    }


class ModelSummary(_Versions):
    """A loaded model, briefly (its default version's fields, and its versions)."""

    name: str
    env_id: str
    context_length: int
    statistic: str
    n_goals: int
    goal_names: list[str]
    discrete_actions: bool


class ModelList(BaseModel):
    """`GET /models`."""

    models: list[ModelSummary]
    model_state: Literal["file", "redis", "off"] = Field(
        "off",
        description="Where each model's default version and canary are kept across restarts: a file in the "
        "folder of checkpoints, the shared Redis store, or nowhere (docs/models.md).",
    )


class ExampleObservation(BaseModel):
    """A real observation of the model's environment (`gmt.service.examples`), to see what one looks like."""

    source: Literal["reset", "mean", "hint"] = Field(
        description="`reset`: the environment's first observation after reset(seed=0), made on the server; "
        "`mean`: the mean observation of the training data (the server has no simulator for the environment); "
        "`hint`: images, described instead of shown."
    )
    description: str = Field(description="Where it comes from, or for images what to send.")
    observation: list[Any] | None = Field(
        description='The observation, ready for `{"observation": ...}` in an act (null for images).'
    )


class ModelOut(
    record_schema(
        ModelInfo,
        types={"observation_space": Space, "action_space": Space, "goals": list[GoalOut]},
        base=_Versions,
    )
):
    """`GET /models/{name}`: spaces, goal table and context length K (of the default version), and the versions."""

    discrete_actions: bool
    example_observation: ExampleObservation | None = Field(
        default=None,
        description="What an observation of this model looks like (where it comes from: `source`).",
    )

    @classmethod
    def of(cls, v: ModelView, example: Example | None = None) -> ModelOut:
        """From the core's view and the model's example observation."""
        return cls(
            **{f.name: getattr(v, f.name) for f in fields(ModelInfo)}
            | {
                "observation_space": Space(**v.observation_space),
                "action_space": Space(**v.action_space),
                "goals": [GoalOut(**asdict(g)) for g in v.goals],
                "action_modes": list(v.action_modes),
            },
            discrete_actions=v.discrete_actions,
            example_observation=None if example is None else ExampleObservation(**asdict(example)),
            **_versions(v),
        )


def summary(v: ModelView) -> ModelSummary:
    """A model's summary from the core's view."""
    return ModelSummary(
        name=v.name,
        env_id=v.env_id,
        context_length=v.context_length,
        statistic=v.statistic,
        n_goals=len(v.goals),
        goal_names=[g.name for g in v.goals],
        discrete_actions=v.discrete_actions,
        **_versions(v),
    )


class CreateSession(_Request):
    """`POST /sessions`: a model and a goal by id or name, or a target statistic value."""

    model: str | None = Field(None, description="Model name; may be omitted when one model is loaded.")
    goal: GoalRef | None = Field(None, description="Goal id or goal name.", examples=[0, "high"])
    target: float | None = Field(None, description="Target statistic value: the nearest goal mean is chosen.")
    seed: JsonInt | None = Field(
        None,
        description="Seed of the session's sampler (sample/expert modes).",
        json_schema_extra={"minimum": 0, "maximum": 2**63 - 1},
    )
    action_mode: Literal["argmax", "sample", "expert", "mean"] | None = Field(
        None,
        description="Discrete actions: expert, argmax or sample. Continuous: mean, or sample (mean + the goal's "
        "calibrated behaviour noise). Omitted: the model's default, the first of the modes `GET /models/{name}` "
        "lists (the checkpoint declares it; else expert for discrete actions, sample for a calibrated continuous "
        "model, mean otherwise).",
    )
    session_id: str | None = Field(
        None,
        description="Your own id for the session (1 to 128 letters, digits, '.', '_', '~', '-'; not '.' or '..'); "
        "the server draws "
        "one when omitted. With it, creating is idempotent: a retry with the same id and body answers the session "
        "the first attempt created (a different body answers 409 already_exists).",
        examples=["bot-7-episode-12"],
    )
    version: StrictStr | None = Field(
        None,
        description="The model version to run for the session's whole life (a serving one); omitted: the model's "
        "default version, or its canary for the canary's share of session ids.",
    )
    record: StrictBool | None = Field(
        None,
        description="Record the episode (observations, actions, goals, reported rewards): `GET "
        "/sessions/{id}/recording` while it lives, a file in the server's --record-dir when it closes or expires. "
        "Omitted: as the server's --record-share draws it. Needs a server started with --record-dir (409 "
        "failed_precondition otherwise).",
    )


class SetGoal(_Request):
    """`PUT /sessions/{id}/goal`."""

    goal: GoalRef | None = Field(None, description="Goal id or goal name.", examples=[2, "low"])
    target: float | None = Field(None, description="Target statistic value: the nearest goal mean is chosen.")
    blend_steps: JsonInt = Field(
        0,
        description="Fade the new goal in over this many steps (0 = at once).",
        json_schema_extra={"minimum": 0, "maximum": MAX_BLEND_STEPS},
    )


class ResetSession(_Request):
    """`POST /sessions/{id}/reset`: optionally a new goal."""

    goal: GoalRef | None = None
    target: float | None = None


class SessionOut(record_schema(SessionInfo, exclude=frozenset({"effective_step"}))):
    """A session's state."""

    @classmethod
    def of(cls, v: SessionView) -> SessionOut:
        """From the core's view."""
        return cls(**{k: x for k, x in vars(v).items() if k != "effective_step"})


class SetGoalOut(SessionOut):
    """A goal change's answer: the session's state and when the change takes effect."""

    effective_step: int = Field(
        description="The step of the first act that uses the new goal (the session's next step)."
    )

    @classmethod
    def of(cls, v: SessionView) -> SetGoalOut:
        """From the core's view of a goal change."""
        return cls(**vars(v))


class TimelineEntry(BaseModel):
    """One goal the session had, from the step of the first act that used it."""

    step: int = Field(description="The step (within its episode) of the first act that used this goal.")
    episode: int = Field(description="The session's episode: 0, then one more at each reset.")
    goal: int
    given: dict[str, int | float | str] = Field(
        description='How the goal was asked for: {"goal": id or name} or {"target": value}; {} for a reset '
        "that kept the goal."
    )
    blend_steps: int
    by: Literal["create", "reset", "rest", "grpc", "stream"]
    at: float = Field(description="Server clock when the change was made (seconds since the epoch).")


class TimelineOut(BaseModel):
    """`GET /sessions/{id}/timeline`: a page of every goal the session had, in order."""

    session_id: str
    model: str
    model_version: str = Field(description="The model version the session runs for its whole life.")
    fingerprint: str | None = Field(description="sha256 of the version's weights and gmt.json.")
    step: int = Field(description="The session's step now (its next act's).")
    episode: int
    entries: int = Field(description="Goal changes made; more than kept once the timeline is full.")
    offset: int = Field(
        description="The index of the first entry listed (the next page starts after the last)."
    )
    goals: list[TimelineEntry] = Field(description="At most `limit` entries from `offset`.")

    @classmethod
    def of(cls, v: TimelineView) -> TimelineOut:
        """From the core's view."""
        return cls(**vars(v))


class RecordingOut(BaseModel):
    """`GET /sessions/{id}/recording`: the recording so far, one entry per answered step in every list
    (docs/records.md; `?format=npz` answers the same as arrays)."""

    session_id: str
    model: str
    model_version: str | None = None
    fingerprint: str | None
    env_id: str | None
    action_mode: str
    seed: int
    created_at: float
    max_steps: int
    stopped: str | None = Field(description="Why the recording stopped before the session ended, or null.")
    steps: int
    episode: list[int]
    t: list[int]
    time: list[float]
    observations: list[Any]
    actions: list[list[float]] | list[int]
    goals: list[int]
    goal_tokens: list[int]
    blend_w: list[float]
    reported: list[bool] = Field(description="Whether the client reported the outcome of each step's action.")
    rewards: list[float | None]
    terminated: list[bool]
    truncated: list[bool]
    infos: dict[str, list[float | None]]
    timeline: list[TimelineEntry]


class Tensor(_Request):
    """A raw little-endian array, base64-encoded (images)."""

    data: str = Field(description="Standard base64 of the array's bytes.")
    dtype: str = Field(description="NumPy dtype name, e.g. uint8 or float32.", examples=["uint8"])
    shape: list[JsonInt]


class Act(_Request):
    """`POST /sessions/{id}/act`: one observation, as (nested) numbers or a base64 tensor."""

    observation: list[Any] | Tensor = Field(examples=[[0.0] * 17])
    step: JsonInt | None = Field(
        None,
        ge=0,
        description="The step this act is for (0 for an episode's first act). A repeat of the last answered "
        "step returns that answer again without stepping (a safe retry); any other mismatch answers 409 "
        "failed_precondition naming the session's step.",
    )
    reward: float | None = Field(
        None,
        description="The reward the environment gave for the previous action (a recorded session keeps it).",
        json_schema_extra={"minimum": -MAX_REPORTED, "maximum": MAX_REPORTED},
    )
    terminated: StrictBool | None = Field(None, description="The previous action ended the episode.")
    truncated: StrictBool | None = Field(None, description="The episode was cut after the previous action.")
    info: dict[StrictStr, float] | None = Field(
        None,
        description=f"The environment's info for the previous action: at most {MAX_INFO_KEYS} numbers, e.g. "
        '{"x_velocity": 1.5}. These four report the outcome of the previous action; an episode\'s first act '
        "has none (409 failed_precondition).",
    )

    @field_validator("observation", mode="before")
    @classmethod
    def _list_or_tensor(cls, v: object) -> object:
        if not isinstance(v, list | dict):
            raise ValueError("must be a list of numbers or an object {data, dtype, shape}")
        return v


class ActItem(Act):
    """One item of `POST /act`: a session and its observation (as in `POST /sessions/{id}/act`)."""

    session_id: StrictStr


class ActMany(_Request):
    """`POST /act`: one step for each of many sessions, in one forward pass; a session may appear once."""

    requests: list[ActItem] = Field(description=f"At most {MAX_ACT_ITEMS} items.")


class ActOut(BaseModel):
    """The action for the observation (a list for Box spaces, an int for Discrete ones); written by
    `gmt.service.rest.act.act_fields`."""

    action: list[float] | int
    step: int
    goal: int
    session_id: str


class ErrorBody(BaseModel):
    """An error's code and message."""

    code: str = Field(examples=["invalid_argument"])
    message: str = Field(examples=["observation has 5 values, expected 17 (shape [17])"])


class ErrorOut(BaseModel):
    """Every error answer: `{"error": {"code", "message"}}`."""

    error: ErrorBody


class ActItemOut(BaseModel):
    """One item of `POST /act`'s answer: the action (as `POST /sessions/{id}/act` answers it) or the error that
    failed this item alone (the same code and message that call would have answered); written by
    `gmt.service.rest.act.many_answer`."""

    session_id: str
    action: list[float] | int | None = None
    step: int | None = None
    goal: int | None = None
    error: ErrorBody | None = None


class ActManyOut(BaseModel):
    """`POST /act`'s answer: one result per request, in request order."""

    results: list[ActItemOut]


class Health(BaseModel):
    """`GET /healthz`."""

    status: str


class Readiness(BaseModel):
    """`GET /readyz` (503 when not ready)."""

    ready: bool
    reason: str | None
    models: list[str]
    errors: dict[str, str]


# ----- model management -----------------------------------------------------------------------------------------
class LoadVersion(_Request):
    """`POST /models/{name}/versions`: a checkpoint directory to load as a version of the model."""

    path: StrictStr = Field(
        description="A checkpoint directory under the server's checkpoint roots (relative paths: from the server's "
        "working directory, else from each root).",
        examples=["checkpoints/halfcheetah-gmt-v2"],
    )
    fingerprint: StrictStr | None = Field(
        None,
        pattern=r"^[0-9a-fA-F]{12,64}$",
        description="Refuse the checkpoint unless its fingerprint starts with these 12 to 64 hex digits.",
    )


class LoadVersionOut(VersionOut):
    """The loaded version (the one already loaded, when the same checkpoint is loaded again)."""

    name: str


class Promote(_Request):
    """`PUT /models/{name}/default`."""

    version: StrictStr = Field(pattern=f"^{VERSION_PATTERN.pattern}$")
    share: float = Field(
        1.0,
        gt=0,
        le=1,
        allow_inf_nan=False,
        description="1: the default version of new sessions. Below 1: a canary that gets this share of the new "
        "sessions that name no version (the default keeps the rest).",
    )


class ModelVersionsOut(_Versions):
    """A model's versions after a change (empty once its last version is unloaded)."""

    name: str

    @classmethod
    def of(cls, v: ModelView) -> ModelVersionsOut:
        """From the core's view."""
        return cls(name=v.name, **_versions(v))
