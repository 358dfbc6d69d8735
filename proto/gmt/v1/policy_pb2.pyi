from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Observation(_message.Message):
    __slots__ = ("values", "tensor")
    VALUES_FIELD_NUMBER: _ClassVar[int]
    TENSOR_FIELD_NUMBER: _ClassVar[int]
    values: FloatVector
    tensor: Tensor
    def __init__(self, values: _Optional[_Union[FloatVector, _Mapping]] = ..., tensor: _Optional[_Union[Tensor, _Mapping]] = ...) -> None: ...

class FloatVector(_message.Message):
    __slots__ = ("values",)
    VALUES_FIELD_NUMBER: _ClassVar[int]
    values: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, values: _Optional[_Iterable[float]] = ...) -> None: ...

class Tensor(_message.Message):
    __slots__ = ("data", "shape", "dtype")
    DATA_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    shape: _containers.RepeatedScalarFieldContainer[int]
    dtype: str
    def __init__(self, data: _Optional[bytes] = ..., shape: _Optional[_Iterable[int]] = ..., dtype: _Optional[str] = ...) -> None: ...

class GoalSelector(_message.Message):
    __slots__ = ("id", "name", "target")
    ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    TARGET_FIELD_NUMBER: _ClassVar[int]
    id: int
    name: str
    target: float
    def __init__(self, id: _Optional[int] = ..., name: _Optional[str] = ..., target: _Optional[float] = ...) -> None: ...

class Space(_message.Message):
    __slots__ = ("type", "shape", "low", "high", "n", "dtype")
    TYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    LOW_FIELD_NUMBER: _ClassVar[int]
    HIGH_FIELD_NUMBER: _ClassVar[int]
    N_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    type: str
    shape: _containers.RepeatedScalarFieldContainer[int]
    low: _containers.RepeatedScalarFieldContainer[float]
    high: _containers.RepeatedScalarFieldContainer[float]
    n: int
    dtype: str
    def __init__(self, type: _Optional[str] = ..., shape: _Optional[_Iterable[int]] = ..., low: _Optional[_Iterable[float]] = ..., high: _Optional[_Iterable[float]] = ..., n: _Optional[int] = ..., dtype: _Optional[str] = ...) -> None: ...

class Goal(_message.Message):
    __slots__ = ("id", "name", "mean", "std", "min", "max", "count")
    ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    MEAN_FIELD_NUMBER: _ClassVar[int]
    STD_FIELD_NUMBER: _ClassVar[int]
    MIN_FIELD_NUMBER: _ClassVar[int]
    MAX_FIELD_NUMBER: _ClassVar[int]
    COUNT_FIELD_NUMBER: _ClassVar[int]
    id: int
    name: str
    mean: float
    std: float
    min: float
    max: float
    count: int
    def __init__(self, id: _Optional[int] = ..., name: _Optional[str] = ..., mean: _Optional[float] = ..., std: _Optional[float] = ..., min: _Optional[float] = ..., max: _Optional[float] = ..., count: _Optional[int] = ...) -> None: ...

class ModelInfo(_message.Message):
    __slots__ = ("name", "env_id", "observation_space", "action_space", "context_length", "statistic", "goals", "preprocessing_json", "action_modes", "switch_relabel_steps", "versions", "default_version", "canary")
    NAME_FIELD_NUMBER: _ClassVar[int]
    ENV_ID_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_SPACE_FIELD_NUMBER: _ClassVar[int]
    ACTION_SPACE_FIELD_NUMBER: _ClassVar[int]
    CONTEXT_LENGTH_FIELD_NUMBER: _ClassVar[int]
    STATISTIC_FIELD_NUMBER: _ClassVar[int]
    GOALS_FIELD_NUMBER: _ClassVar[int]
    PREPROCESSING_JSON_FIELD_NUMBER: _ClassVar[int]
    ACTION_MODES_FIELD_NUMBER: _ClassVar[int]
    SWITCH_RELABEL_STEPS_FIELD_NUMBER: _ClassVar[int]
    VERSIONS_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_VERSION_FIELD_NUMBER: _ClassVar[int]
    CANARY_FIELD_NUMBER: _ClassVar[int]
    name: str
    env_id: str
    observation_space: Space
    action_space: Space
    context_length: int
    statistic: str
    goals: _containers.RepeatedCompositeFieldContainer[Goal]
    preprocessing_json: str
    action_modes: _containers.RepeatedScalarFieldContainer[str]
    switch_relabel_steps: int
    versions: _containers.RepeatedCompositeFieldContainer[ModelVersion]
    default_version: str
    canary: Canary
    def __init__(self, name: _Optional[str] = ..., env_id: _Optional[str] = ..., observation_space: _Optional[_Union[Space, _Mapping]] = ..., action_space: _Optional[_Union[Space, _Mapping]] = ..., context_length: _Optional[int] = ..., statistic: _Optional[str] = ..., goals: _Optional[_Iterable[_Union[Goal, _Mapping]]] = ..., preprocessing_json: _Optional[str] = ..., action_modes: _Optional[_Iterable[str]] = ..., switch_relabel_steps: _Optional[int] = ..., versions: _Optional[_Iterable[_Union[ModelVersion, _Mapping]]] = ..., default_version: _Optional[str] = ..., canary: _Optional[_Union[Canary, _Mapping]] = ...) -> None: ...

class ModelVersion(_message.Message):
    __slots__ = ("version", "sessions", "state", "fingerprint")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    SESSIONS_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    FINGERPRINT_FIELD_NUMBER: _ClassVar[int]
    version: str
    sessions: int
    state: str
    fingerprint: str
    def __init__(self, version: _Optional[str] = ..., sessions: _Optional[int] = ..., state: _Optional[str] = ..., fingerprint: _Optional[str] = ...) -> None: ...

class Canary(_message.Message):
    __slots__ = ("version", "share")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    SHARE_FIELD_NUMBER: _ClassVar[int]
    version: str
    share: float
    def __init__(self, version: _Optional[str] = ..., share: _Optional[float] = ...) -> None: ...

class SessionInfo(_message.Message):
    __slots__ = ("session_id", "model", "goal", "goal_name", "step", "context_size", "blend_remaining", "idle_timeout_s", "action_mode", "context_goals", "expires_in_s", "blend_from", "model_version", "effective_step", "recording")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    GOAL_FIELD_NUMBER: _ClassVar[int]
    GOAL_NAME_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    CONTEXT_SIZE_FIELD_NUMBER: _ClassVar[int]
    BLEND_REMAINING_FIELD_NUMBER: _ClassVar[int]
    IDLE_TIMEOUT_S_FIELD_NUMBER: _ClassVar[int]
    ACTION_MODE_FIELD_NUMBER: _ClassVar[int]
    CONTEXT_GOALS_FIELD_NUMBER: _ClassVar[int]
    EXPIRES_IN_S_FIELD_NUMBER: _ClassVar[int]
    BLEND_FROM_FIELD_NUMBER: _ClassVar[int]
    MODEL_VERSION_FIELD_NUMBER: _ClassVar[int]
    EFFECTIVE_STEP_FIELD_NUMBER: _ClassVar[int]
    RECORDING_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    model: str
    goal: int
    goal_name: str
    step: int
    context_size: int
    blend_remaining: int
    idle_timeout_s: float
    action_mode: str
    context_goals: _containers.RepeatedScalarFieldContainer[int]
    expires_in_s: float
    blend_from: int
    model_version: str
    effective_step: int
    recording: bool
    def __init__(self, session_id: _Optional[str] = ..., model: _Optional[str] = ..., goal: _Optional[int] = ..., goal_name: _Optional[str] = ..., step: _Optional[int] = ..., context_size: _Optional[int] = ..., blend_remaining: _Optional[int] = ..., idle_timeout_s: _Optional[float] = ..., action_mode: _Optional[str] = ..., context_goals: _Optional[_Iterable[int]] = ..., expires_in_s: _Optional[float] = ..., blend_from: _Optional[int] = ..., model_version: _Optional[str] = ..., effective_step: _Optional[int] = ..., recording: _Optional[bool] = ...) -> None: ...

class ListModelsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListModelsResponse(_message.Message):
    __slots__ = ("models",)
    MODELS_FIELD_NUMBER: _ClassVar[int]
    models: _containers.RepeatedCompositeFieldContainer[ModelInfo]
    def __init__(self, models: _Optional[_Iterable[_Union[ModelInfo, _Mapping]]] = ...) -> None: ...

class GetModelRequest(_message.Message):
    __slots__ = ("name",)
    NAME_FIELD_NUMBER: _ClassVar[int]
    name: str
    def __init__(self, name: _Optional[str] = ...) -> None: ...

class CreateSessionRequest(_message.Message):
    __slots__ = ("model", "goal", "seed", "action_mode", "session_id", "version", "record")
    MODEL_FIELD_NUMBER: _ClassVar[int]
    GOAL_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    ACTION_MODE_FIELD_NUMBER: _ClassVar[int]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    RECORD_FIELD_NUMBER: _ClassVar[int]
    model: str
    goal: GoalSelector
    seed: int
    action_mode: str
    session_id: str
    version: str
    record: bool
    def __init__(self, model: _Optional[str] = ..., goal: _Optional[_Union[GoalSelector, _Mapping]] = ..., seed: _Optional[int] = ..., action_mode: _Optional[str] = ..., session_id: _Optional[str] = ..., version: _Optional[str] = ..., record: _Optional[bool] = ...) -> None: ...

class GetSessionRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class ActRequest(_message.Message):
    __slots__ = ("session_id", "values", "tensor", "step", "reward", "terminated", "truncated", "info")
    class InfoEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    TENSOR_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    REWARD_FIELD_NUMBER: _ClassVar[int]
    TERMINATED_FIELD_NUMBER: _ClassVar[int]
    TRUNCATED_FIELD_NUMBER: _ClassVar[int]
    INFO_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    values: FloatVector
    tensor: Tensor
    step: int
    reward: float
    terminated: bool
    truncated: bool
    info: _containers.ScalarMap[str, float]
    def __init__(self, session_id: _Optional[str] = ..., values: _Optional[_Union[FloatVector, _Mapping]] = ..., tensor: _Optional[_Union[Tensor, _Mapping]] = ..., step: _Optional[int] = ..., reward: _Optional[float] = ..., terminated: _Optional[bool] = ..., truncated: _Optional[bool] = ..., info: _Optional[_Mapping[str, float]] = ...) -> None: ...

class ActResponse(_message.Message):
    __slots__ = ("action", "discrete_action", "is_discrete", "step", "goal", "session_id")
    ACTION_FIELD_NUMBER: _ClassVar[int]
    DISCRETE_ACTION_FIELD_NUMBER: _ClassVar[int]
    IS_DISCRETE_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    GOAL_FIELD_NUMBER: _ClassVar[int]
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    action: _containers.RepeatedScalarFieldContainer[float]
    discrete_action: int
    is_discrete: bool
    step: int
    goal: int
    session_id: str
    def __init__(self, action: _Optional[_Iterable[float]] = ..., discrete_action: _Optional[int] = ..., is_discrete: _Optional[bool] = ..., step: _Optional[int] = ..., goal: _Optional[int] = ..., session_id: _Optional[str] = ...) -> None: ...

class ActBatchRequest(_message.Message):
    __slots__ = ("requests",)
    REQUESTS_FIELD_NUMBER: _ClassVar[int]
    requests: _containers.RepeatedCompositeFieldContainer[ActRequest]
    def __init__(self, requests: _Optional[_Iterable[_Union[ActRequest, _Mapping]]] = ...) -> None: ...

class ActBatchError(_message.Message):
    __slots__ = ("code", "message")
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    code: str
    message: str
    def __init__(self, code: _Optional[str] = ..., message: _Optional[str] = ...) -> None: ...

class ActBatchResult(_message.Message):
    __slots__ = ("session_id", "action", "error")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    action: ActResponse
    error: ActBatchError
    def __init__(self, session_id: _Optional[str] = ..., action: _Optional[_Union[ActResponse, _Mapping]] = ..., error: _Optional[_Union[ActBatchError, _Mapping]] = ...) -> None: ...

class ActBatchResponse(_message.Message):
    __slots__ = ("results",)
    RESULTS_FIELD_NUMBER: _ClassVar[int]
    results: _containers.RepeatedCompositeFieldContainer[ActBatchResult]
    def __init__(self, results: _Optional[_Iterable[_Union[ActBatchResult, _Mapping]]] = ...) -> None: ...

class SetGoalRequest(_message.Message):
    __slots__ = ("session_id", "goal", "blend_steps")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    GOAL_FIELD_NUMBER: _ClassVar[int]
    BLEND_STEPS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    goal: GoalSelector
    blend_steps: int
    def __init__(self, session_id: _Optional[str] = ..., goal: _Optional[_Union[GoalSelector, _Mapping]] = ..., blend_steps: _Optional[int] = ...) -> None: ...

class ResetSessionRequest(_message.Message):
    __slots__ = ("session_id", "goal")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    GOAL_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    goal: GoalSelector
    def __init__(self, session_id: _Optional[str] = ..., goal: _Optional[_Union[GoalSelector, _Mapping]] = ...) -> None: ...

class GetTimelineRequest(_message.Message):
    __slots__ = ("session_id", "offset", "limit")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    LIMIT_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    offset: int
    limit: int
    def __init__(self, session_id: _Optional[str] = ..., offset: _Optional[int] = ..., limit: _Optional[int] = ...) -> None: ...

class TimelineEntry(_message.Message):
    __slots__ = ("step", "episode", "goal", "given", "blend_steps", "by", "at")
    STEP_FIELD_NUMBER: _ClassVar[int]
    EPISODE_FIELD_NUMBER: _ClassVar[int]
    GOAL_FIELD_NUMBER: _ClassVar[int]
    GIVEN_FIELD_NUMBER: _ClassVar[int]
    BLEND_STEPS_FIELD_NUMBER: _ClassVar[int]
    BY_FIELD_NUMBER: _ClassVar[int]
    AT_FIELD_NUMBER: _ClassVar[int]
    step: int
    episode: int
    goal: int
    given: GoalSelector
    blend_steps: int
    by: str
    at: float
    def __init__(self, step: _Optional[int] = ..., episode: _Optional[int] = ..., goal: _Optional[int] = ..., given: _Optional[_Union[GoalSelector, _Mapping]] = ..., blend_steps: _Optional[int] = ..., by: _Optional[str] = ..., at: _Optional[float] = ...) -> None: ...

class Timeline(_message.Message):
    __slots__ = ("session_id", "model", "fingerprint", "step", "episode", "entries", "goals", "model_version", "offset")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    FINGERPRINT_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    EPISODE_FIELD_NUMBER: _ClassVar[int]
    ENTRIES_FIELD_NUMBER: _ClassVar[int]
    GOALS_FIELD_NUMBER: _ClassVar[int]
    MODEL_VERSION_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    model: str
    fingerprint: str
    step: int
    episode: int
    entries: int
    goals: _containers.RepeatedCompositeFieldContainer[TimelineEntry]
    model_version: str
    offset: int
    def __init__(self, session_id: _Optional[str] = ..., model: _Optional[str] = ..., fingerprint: _Optional[str] = ..., step: _Optional[int] = ..., episode: _Optional[int] = ..., entries: _Optional[int] = ..., goals: _Optional[_Iterable[_Union[TimelineEntry, _Mapping]]] = ..., model_version: _Optional[str] = ..., offset: _Optional[int] = ...) -> None: ...

class CloseSessionRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class CloseSessionResponse(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class ControlRequest(_message.Message):
    __slots__ = ("act", "set_goal", "reset")
    ACT_FIELD_NUMBER: _ClassVar[int]
    SET_GOAL_FIELD_NUMBER: _ClassVar[int]
    RESET_FIELD_NUMBER: _ClassVar[int]
    act: ActRequest
    set_goal: SetGoalRequest
    reset: ResetSessionRequest
    def __init__(self, act: _Optional[_Union[ActRequest, _Mapping]] = ..., set_goal: _Optional[_Union[SetGoalRequest, _Mapping]] = ..., reset: _Optional[_Union[ResetSessionRequest, _Mapping]] = ...) -> None: ...

class ControlError(_message.Message):
    __slots__ = ("code", "message")
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    code: str
    message: str
    def __init__(self, code: _Optional[str] = ..., message: _Optional[str] = ...) -> None: ...

class ControlResponse(_message.Message):
    __slots__ = ("act", "session", "error")
    ACT_FIELD_NUMBER: _ClassVar[int]
    SESSION_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    act: ActResponse
    session: SessionInfo
    error: ControlError
    def __init__(self, act: _Optional[_Union[ActResponse, _Mapping]] = ..., session: _Optional[_Union[SessionInfo, _Mapping]] = ..., error: _Optional[_Union[ControlError, _Mapping]] = ...) -> None: ...
