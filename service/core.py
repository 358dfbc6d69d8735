"""The transport-agnostic service: models and their versions, sessions, goals and batched actions. Both adapters
call this."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import logging
import math
import re
import time
import uuid
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gmt.common.recording import Recording
from gmt.model.checkpoint import VERSION_PATTERN, CheckpointError, Goal
from gmt.model.context import Context
from gmt.model.engine import InvalidObservation, StepFailed, check_blend_steps
from gmt.service import keys
from gmt.service.batcher import MicroBatcher
from gmt.service.console.activity import SessionRow
from gmt.service.console.events import EventHub
from gmt.service.errors import (
    Aborted,
    AlreadyExists,
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    PermissionDenied,
    ServiceError,
    Unavailable,
)
from gmt.service.metrics import Metrics
from gmt.service.model_state import ModelState, NoModelState, entry_of, model_state_for, restore
from gmt.service.observations import MAX_ABS_VALUE, to_array
from gmt.service.records import BY, Layout, Report, assemble, decode_timeline, record_drawn
from gmt.service.registry import (
    DRAINING,
    LoadedModel,
    ModelRegistry,
    ModelVersions,
    find_by_fingerprint,
    load_model,
    model_key,
)
from gmt.service.sessions import Clock, MemorySessionStore, Session, SessionStore
from gmt.service.settings import Settings
from gmt.service.units import point_of_no_return, run_whole

log = logging.getLogger("gmt.core")


def short_id(sid: str) -> str:
    """A session id as logs show it: its first 8 characters (a whole id is a bearer of the session)."""
    return sid[:8] + "..." if len(sid) > 8 else sid


MAX_ID_LENGTH = 128  # the longest session id accepted (the server issues 32 hex digits)
MAX_PATH_LENGTH = 4096  # the longest checkpoint path a load accepts (Linux PATH_MAX)
# Names an HTTP client rewrites in a path (RFC 3986 5.2.4), so never a session's or a model's.
DOT_SEGMENTS = (".", "..")
# A client-chosen session id: URL-unreserved characters, one spelling in any path.
SESSION_ID_PATTERN = rf"[A-Za-z0-9._~-]{{1,{MAX_ID_LENGTH}}}"
_CLIENT_ID = re.compile(SESSION_ID_PATTERN)


def check_session_id(sid: object) -> str:
    """`sid` if it can name a session; the one owner of that rule for every call that names one.

    An id too long to be one is refused without echoing it (an attacker's 200k characters must not come back in
    a header, a message or gRPC metadata).

    Raises:
        NotFound: not a string, empty, or longer than `MAX_ID_LENGTH`.
    """
    if not isinstance(sid, str) or not sid:
        raise NotFound("session id is empty: name a session created with POST /sessions")
    if len(sid) > MAX_ID_LENGTH:
        raise NotFound(f"no session has an id of {len(sid)} characters (ids are at most {MAX_ID_LENGTH})")
    return sid


def echoed_id(sid: str) -> str:
    """`sid` as an answer may repeat it: itself when it could name a session, else "" (an item of a many-session
    act then names its index; an attacker's 200k characters never come back)."""
    return sid if isinstance(sid, str) and len(sid) <= MAX_ID_LENGTH else ""


def check_new_session_id(sid: str) -> str:
    """A client-chosen id for a new session: 1 to 128 URL-unreserved characters (letters, digits, `._~-`), not
    `.` or `..`.

    Raises:
        InvalidArgument: anything else (the id is not echoed when it is too long).
    """
    if not isinstance(sid, str) or not _CLIENT_ID.fullmatch(sid):
        shown = repr(sid) if isinstance(sid, str) and len(sid) <= MAX_ID_LENGTH else "given"
        raise InvalidArgument(
            f"session_id {shown} is not 1 to {MAX_ID_LENGTH} characters of letters, digits, '.', '_', '~' or '-'"
        )
    if sid in DOT_SEGMENTS:
        raise InvalidArgument(
            f"session_id {sid!r} cannot be addressed: HTTP clients rewrite /sessions/{sid}/act to another path"
        )
    return sid


MAX_ACT_ITEMS = 4096  # most (session, observation) items in one many-session act (POST /act, gRPC ActBatch)
UNLOAD_WAIT_S = 5.0  # longest wait, in a forced unload, for the acts already in the version's batcher
MAX_LIST_SESSIONS = 500  # the longest page of `list_sessions`
MAX_LIST_OFFSET = 10**9  # the largest offset of `list_sessions` (far past any store; larger overflow int64)
MAX_TIMELINE_PAGE = 1000  # the longest page of `timeline` (and its default)
GoalRef = int | str | None
_HEX = re.compile(r"[0-9a-fA-F]{12,64}")
_MODEL_NAME = re.compile(r"[A-Za-z0-9._-]{1,128}")


def check_version(version: object, what: str = "version") -> str:
    """`version` if it can name a model version (1 to 64 letters, digits, '.', '_', '-').

    Raises:
        InvalidArgument: anything else.
    """
    if not isinstance(version, str) or not VERSION_PATTERN.fullmatch(version):
        shown = repr(version) if isinstance(version, str) and len(version) <= 64 else "given"
        raise InvalidArgument(f"{what} {shown} is not 1 to 64 letters, digits, '.', '_' or '-'")
    return version


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
class ModelView:
    """What clients learn about a model: its default version's spaces and goals, and its version table."""

    name: str
    env_id: str
    observation_space: dict
    action_space: dict
    context_length: int
    statistic: str
    goals: list[Goal]
    discrete_actions: bool
    action_modes: tuple[str, ...]  # the first is the default
    preprocessing: dict | None = None  # the observation pipeline of the training data (Atari frames)
    switch_relabel_steps: int = 0  # past steps a goal change at once relabels (`PolicyEngine.set_goal`)
    version: str = ""  # the version this view describes (the default)
    versions: tuple[VersionView, ...] = ()
    default_version: str = ""
    canary: tuple[str, float] | None = None  # (version, share of new sessions)


@dataclass(frozen=True)
class SessionView:
    """What clients learn about a session.

    Attributes:
        goal: The goal the session pursues (the target of a running blend).
        blend_from: The goal being faded out (equal to `goal` when no blend runs).
        context_goals: Goal token of each step in the context, oldest first.
        expires_in_s: Seconds left before the idle timeout ends the session.
        recording: Whether the session records its episode.
        effective_step: For a goal change, the step of the first act that uses the new goal (else None).
    """

    session_id: str
    model: str
    model_version: str
    goal: int
    goal_name: str
    step: int
    context_size: int
    blend_remaining: int
    blend_from: int
    action_mode: str
    idle_timeout_s: float
    expires_in_s: float
    context_goals: list[int]
    recording: bool = False
    effective_step: int | None = None


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


class Core:
    """Loads models, keeps sessions and answers requests; knows nothing of HTTP or gRPC.

    Args:
        settings: Server settings.
        registry: Models to serve (default: loaded from `settings.checkpoints` by `start`).
        store: Session store (default: Redis if `settings.redis_url`, else memory).
        clock: Wall-clock seconds used for idle timeouts (injectable for tests).
    """

    def __init__(
        self,
        settings: Settings,
        registry: ModelRegistry | None = None,
        store: SessionStore | None = None,
        clock: Clock = time.time,
    ) -> None:
        self.settings = settings
        self.registry = registry
        self.store = store
        self.clock = clock
        self.metrics = Metrics()
        self.keyring = keys.Keyring.of(settings)  # the adapters identify callers by it (`gmt.service.keys`)
        self.started = False
        self.closing = False
        self._closed = False
        self._batchers: dict[str, MicroBatcher] = {}  # by `LoadedModel.key`
        self._executor: ThreadPoolExecutor | None = None
        self._admin = asyncio.Lock()  # one model change (load, adopt, promote, drain, unload) at a time
        self._adopting: dict[str, asyncio.Future] = {}  # key -> the load of a version a session needs
        self._unloaded: set[str] = set()  # keys unloaded with force: their sessions are refused here
        self._tasks: set[asyncio.Task] = set()  # unloads of drained versions in progress
        self._locks: weakref.WeakValueDictionary[str, asyncio.Lock] = weakref.WeakValueDictionary()
        self._sweeper: asyncio.Task | None = None
        self.events = EventHub()  # per-session event feeds of this replica (`GET /sessions/{id}/events`)
        self._archives: set[asyncio.Task] = set()  # recordings being written (expired sessions)
        self.model_state: ModelState = NoModelState()  # where each model's default and canary are kept

    # ----- lifecycle ----------------------------------------------------------------------------------------
    async def start(self) -> None:
        """Load models (in a thread), open the session store and start the batchers and the idle sweeper."""
        import torch

        s = self.settings
        torch.set_num_threads(s.inference_threads)
        from_roots = self.registry is None  # a registry given in memory keeps no state across restarts
        if self.registry is None:
            missing = [str(p) for p in s.checkpoints if not p.exists()]
            if missing:
                log.warning("checkpoint path does not exist", extra={"paths": missing})
            self.registry = await asyncio.to_thread(
                ModelRegistry.load, list(s.checkpoints), s.naive, **self._engine_placement()
            )
        if not self.registry.models:
            log.warning(
                "no model loaded: no checkpoint directory (one with gmt.json) under the checkpoint paths; "
                "serving anyway, /readyz and gRPC health answer not ready",
                extra={"checkpoints": [str(p) for p in s.checkpoints]},
            )
        if self.store is None:
            if s.redis_url:
                from gmt.service.redis_store import store_for

                self.store = store_for(s, self.clock)
                await self.store.ping()
            else:
                self.store = MemorySessionStore(s.idle_timeout_s, s.max_sessions, self.clock)
        self.store.on_remove = self._dropped
        self.store.on_expire = self._expiring
        if from_roots:
            await self._restore_model_state()
        # The naive server is the reference: one request at a time, computed on the event loop.
        self._executor = (
            None if s.naive else ThreadPoolExecutor(s.inference_threads, thread_name_prefix="gmt-infer")
        )
        for m in self.registry.loaded():
            self._start_batcher(m)
        self._sweeper = asyncio.get_running_loop().create_task(self._sweep_forever(), name="session-sweeper")
        self.started = True

    async def _restore_model_state(self) -> None:
        """Serve the defaults and canaries saved before a restart (`gmt.service.model_state`)."""
        self.model_state = model_state_for(list(self.settings.checkpoints), self.store)
        try:
            saved = await self.model_state.read()
        except (OSError, ValueError, ServiceError) as e:
            log.error(
                "saved model state unreadable", extra={"where": self.model_state.where, "error": str(e)}
            )
            return
        roots = list(self.settings.checkpoints)
        await restore(self.registry, saved, roots, self.settings.naive, self.checkpoint_path)

    async def _save_model_state(self, name: str) -> None:
        """Keep model `name`'s default and canary for the next start (a failure is logged: the change stands)."""
        mv = self.registry.names.get(name)
        try:
            await self.model_state.write(name, entry_of(mv) if mv is not None else None)
        except (OSError, ServiceError) as e:
            log.error(
                "model state not saved: a restart serves the previous default",
                extra={"model": name, "where": self.model_state.where, "error": str(e)},
            )

    async def close(self) -> None:
        """Stop batching and sweeping and release the store (sessions in memory are dropped); idempotent."""
        if self._closed:
            return
        self._closed = self.closing = True
        self.events.close()
        if self._sweeper is not None:
            self._sweeper.cancel()
            await asyncio.gather(self._sweeper, return_exceptions=True)
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for b in self._batchers.values():
            await b.close()
        if isinstance(self.store, MemorySessionStore) and self.settings.record_dir is not None:
            for s in self.store.live():  # sessions in memory end with the process: keep their recordings
                if s.ledger.recording:
                    self._archive_soon(
                        s, list(s.ledger.timeline or ()), list(s.ledger.records or ()), "shutdown"
                    )
        if self._archives:
            await asyncio.gather(*self._archives, return_exceptions=True)
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
        if self.store is not None:
            await self.store.close()

    @property
    def ready(self) -> bool:
        """Whether at least one model is loaded and the server is not shutting down."""
        return self.started and not self.closing and bool(self.registry and self.registry.models)

    def readiness(self) -> dict:
        """Readiness and why: loaded models, load errors, closing flag."""
        reg = self.registry or ModelRegistry()
        reason = None
        if self.closing:
            reason = "shutting down"
        elif not self.started:
            reason = "starting"
        elif not reg.models:
            reason = "no model loaded"
        elif not all(b.healthy for b in self._batchers.values()):
            reason = "a batcher is not running"
        # Load errors by checkpoint name: readiness is public and must not reveal file paths.
        errors = {Path(k).name: v.replace(k, Path(k).name) for k, v in reg.errors.items()}
        return {"ready": reason is None, "reason": reason, "models": sorted(reg.models), "errors": errors}

    async def _sweep_forever(self) -> None:
        period = min(max(self.settings.idle_timeout_s / 2, 0.05), 30.0)
        while True:
            await asyncio.sleep(period)
            try:
                await self.sweep()
            except ServiceError as e:
                log.warning("session sweep failed", extra={"error": e.message})

    async def sweep(self) -> int:
        """Remove idle sessions now; returns how many expired."""
        gone = await self.store.sweep()
        for s in gone:
            self._dropped(s.id, s.key)
            self.events.end(s.id, "expired", {"session_id": s.id})
            log.info("session expired", extra={"session": short_id(s.id), "model": s.key})
        for m in self.registry.loaded():  # a shared store lets go of sessions it stopped seeing
            self._unload_if_drained(m)
        self.metrics.sessions_expired.inc(len(gone))
        self.metrics.live_sessions.set(await self.store.count())
        return len(gone)

    # ----- models -------------------------------------------------------------------------------------------
    def _view_model(self, mv: ModelVersions) -> ModelView:
        m = mv.versions[mv.default]
        c = m.checkpoint
        return ModelView(
            name=m.name,
            env_id=c.env_id,
            observation_space=c.observation_space,
            action_space=c.action_space,
            context_length=c.config.context_length,
            statistic=c.statistic,
            goals=list(c.goals),
            discrete_actions=c.config.discrete_actions,
            action_modes=m.engine.describe().action_modes,
            preprocessing=c.preprocessing,
            switch_relabel_steps=m.engine.switch_relabel_steps,
            version=m.version,
            versions=tuple(
                VersionView(v.version, self.store.local_count(v.key), v.state, v.fingerprint)
                for v in mv.versions.values()
            ),
            default_version=mv.default,
            canary=mv.canary,
        )

    def list_models(self) -> list[ModelView]:
        """Every loaded model, by name."""
        return [self._view_model(self.registry.names[n]) for n in sorted(self.registry.names)]

    def get_model(self, name: str) -> ModelView:
        """One model. Raises NotFound."""
        return self._view_model(self.registry.entry(name))

    def _engine_placement(self) -> dict:
        """Where a loaded version's engine runs: `--device`, its pool sized for `--max-sessions` off the CPU."""
        return {"device": self.settings.device, "n_slots": self.settings.max_sessions}

    def _start_batcher(self, m: LoadedModel) -> None:
        """Start the micro-batcher of a version newly in the registry."""
        s = self.settings
        b = MicroBatcher(
            m.engine,
            self._executor,
            max_batch=1 if s.naive else s.max_batch,
            max_wait_s=0.0 if s.naive else s.batch_wait_ms / 1000.0,
            observe=lambda size, sec, n=m.name, v=m.version: self.metrics.observe_batch(n, v, size, sec),
            inline_alone=m.engine.describe().kernel == "native",
        )
        b.start()
        self.metrics.track_queue(m.name, m.version, lambda b=b: b.queued)
        self._batchers[m.key] = b
        self._count_models()

    def _count_models(self) -> None:
        self.metrics.models_loaded.set(len(self.registry.names))
        self.metrics.versions_loaded.set(len(self._batchers))

    def _batcher(self, m: LoadedModel) -> MicroBatcher:
        b = self._batchers.get(m.key)
        if b is None:
            raise FailedPrecondition(
                f"version {m.version!r} of model {m.name!r} was unloaded from this server"
            )
        return b

    async def _stop(self, m: LoadedModel, wait_s: float = 0.0) -> None:
        """Stop serving a version taken out of the registry: its batcher ends (after the acts it holds, for up to
        `wait_s`), and with the last reference the engine, its weights and its session pool are freed."""
        b = self._batchers.pop(m.key, None)
        self.metrics.untrack_queue(m.name, m.version)
        self._count_models()
        if b is not None:
            await b.close(wait_s)
        log.info("model version unloaded", extra={"model": m.name, "version": m.version})

    def _unload_if_drained(self, m: LoadedModel) -> None:
        """Unload a draining version once this server holds none of its sessions."""
        if m.state != DRAINING or self.store.local_count(m.key) or self.closing:
            return
        if self.registry.find(m.name, m.version) is not m:
            return  # already out
        self.registry.remove(m.name, m.version)
        task = asyncio.get_running_loop().create_task(self._stop(m), name=f"unload {m.key}")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def checkpoint_path(self, path: object) -> Path:
        """The checkpoint directory `path` names, if it is under a checkpoint root (`settings.checkpoints`).

        A relative path is taken from the server's working directory, else from each root.

        Raises:
            InvalidArgument: not a non-empty string, or nothing by that name under the roots or elsewhere.
            PermissionDenied: it is not under a checkpoint root (symbolic links resolved).
        """
        if not isinstance(path, str) or not path or "\0" in path:
            raise InvalidArgument("path must name a checkpoint directory under the checkpoint roots")
        if len(path) > MAX_PATH_LENGTH:
            raise InvalidArgument(
                f"path is {len(path)} characters long: a checkpoint path has at most {MAX_PATH_LENGTH}"
            )
        roots = [r.resolve() for r in self.settings.checkpoints]
        p = Path(path)
        tries = [p] if p.is_absolute() else [Path.cwd() / p, *(r / p for r in roots)]
        shown = ", ".join(str(r) for r in self.settings.checkpoints)
        try:
            found = [t.resolve() for t in tries]
            inside = [t for t in found if any(t == r or t.is_relative_to(r) for r in roots)]
            for t in inside:
                if t.exists():
                    return t
            if inside and not any(t.exists() for t in found):
                raise InvalidArgument(f"no checkpoint {path!r} under the checkpoint roots ({shown})")
        except OSError as e:  # a name longer than the file system allows, a loop of links, ...
            raise InvalidArgument(f"path {path!r} cannot name a checkpoint directory: {e.strerror}") from None
        raise PermissionDenied(
            f"{path!r} is not under the checkpoint roots ({shown}): this server loads checkpoints from there only"
        )

    async def load_version(self, name: str, path: str, fingerprint: str | None = None) -> VersionView:
        """Load the checkpoint at `path` as a version of model `name` (a new name starts a new model); the load
        runs in a thread, so acts keep being answered. Loading the version again is answered the loaded one.

        Args:
            fingerprint: Refuse the checkpoint unless its fingerprint starts with this (12 to 64 hex digits).

        Raises:
            InvalidArgument: a bad name or fingerprint, a checkpoint that cannot be loaded (the message names the
                problem), or spaces that differ from the model's default version.
            PermissionDenied: `path` is not under a checkpoint root.
            AlreadyExists: the version is loaded from another checkpoint (another fingerprint).
        """
        self._check_serving()
        if not isinstance(name, str) or not (
            name in self.registry.names or (_MODEL_NAME.fullmatch(name) and name not in DOT_SEGMENTS)
        ):
            raise InvalidArgument(
                "a new model's name must be 1 to 128 letters, digits, '.', '_' or '-', and not '.' or '..' "
                "(HTTP clients rewrite those in a path)"
            )
        if fingerprint is not None and not (isinstance(fingerprint, str) and _HEX.fullmatch(fingerprint)):
            raise InvalidArgument(
                "fingerprint must be 12 to 64 hex digits (a prefix of the checkpoint's sha256)"
            )
        d = self.checkpoint_path(path)
        async with self._admin:
            try:
                m = await asyncio.to_thread(
                    load_model, name, d, self.settings.naive, fingerprint, **self._engine_placement()
                )
            except CheckpointError as e:
                raise InvalidArgument(f"checkpoint refused: {e}") from None
            except OSError as e:  # unreadable files (permissions, a directory where a file should be, ...)
                raise InvalidArgument(
                    f"checkpoint refused: cannot read {e.filename or d}: {e.strerror}"
                ) from None
            have = self.registry.add(m)
            self._unloaded.discard(m.key)
            if have is m:
                self._start_batcher(m)
                log.info("model version added", extra={"model": name, "version": m.version, "path": str(d)})
                if self.registry.names[name].default == m.version:
                    await self._save_model_state(name)  # a new model: its first version is its default
        return self._view_version(have)

    def _view_version(self, m: LoadedModel) -> VersionView:
        return VersionView(m.version, self.store.local_count(m.key), m.state, m.fingerprint)

    async def promote(self, name: str, version: str, share: float = 1.0) -> ModelView:
        """Make `version` the default of model `name` (share 1), or a canary that gets `share` of the new sessions
        that name no version.

        Raises:
            InvalidArgument: share not in (0, 1], or a canary share for the default version.
            NotFound: no such model or version on this server.
        """
        self._check_serving()
        async with self._admin:
            self.registry.promote(name, check_version(version), share)
            await self._save_model_state(name)
        log.info("model version promoted", extra={"model": name, "version": version, "share": share})
        return self.get_model(name)

    async def drain(self, name: str, version: str) -> ModelView:
        """Give `version` no new sessions; it is unloaded once this server holds none of its sessions.

        Raises:
            FailedPrecondition: it is the default version.
            NotFound: no such model or version on this server.
        """
        self._check_serving()
        async with self._admin:
            m = self.registry.drain(name, check_version(version))
            log.info("model version draining", extra={"model": name, "version": version})
            await self._save_model_state(name)  # a drained canary is no longer one
            self._unload_if_drained(m)
        return self.get_model(name) if name in self.registry.names else self._gone(name)

    async def unload(self, name: str, version: str, force: bool = False) -> ModelView:
        """Unload `version` now. With `force`, also while sessions use it: their next calls here answer
        failed_precondition (until the version is loaded again).

        Raises:
            FailedPrecondition: sessions use it (and not `force`), or it is the default while other versions are
                loaded.
            NotFound: no such model or version on this server.
        """
        self._check_serving()
        async with self._admin:
            m = self.registry.version(name, check_version(version))
            n = self.store.local_count(m.key)
            if n and not force:
                raise FailedPrecondition(
                    f"{n} session(s) on this server use version {version!r} of model {name!r}: drain it (it is "
                    "unloaded when they end), or unload with force=true (their next calls fail)"
                )
            self.registry.remove(name, version)
            await self._save_model_state(name)
            if n:
                self._unloaded.add(m.key)
            await self._stop(m, wait_s=UNLOAD_WAIT_S)
        return self.get_model(name) if name in self.registry.names else self._gone(name)

    @staticmethod
    def _gone(name: str) -> ModelView:
        """The view of a model whose last version was unloaded: no versions."""
        return ModelView(name, "", {}, {}, 0, "", [], False, ())

    async def _model_of(self, s: Session) -> LoadedModel:
        """The loaded version a session runs; a version this server lacks is found under the checkpoint roots by
        its fingerprint and loaded (in a thread).

        Raises:
            FailedPrecondition: this server does not serve the model, or the version was unloaded here with
                force, or it cannot be found or loaded.
        """
        if s.model not in self.registry.names:
            raise FailedPrecondition(
                f"session {s.id!r} runs model {s.model!r}, which this server does not serve"
            )
        m = self.registry.find(s.model, s.model_version)
        if m is not None:
            if s.fingerprint and m.fingerprint and m.fingerprint != s.fingerprint:
                raise FailedPrecondition(
                    f"session {s.id!r} runs version {s.model_version!r} of model {s.model!r} with fingerprint "
                    f"{s.fingerprint[:16]}..., but this server's version {m.version!r} has fingerprint "
                    f"{m.fingerprint[:16]}..."
                )
            return m
        key = model_key(s.model, s.model_version)
        if key in self._unloaded:
            raise FailedPrecondition(
                f"session {s.id!r} runs version {s.model_version!r} of model {s.model!r}, which was unloaded from "
                "this server (forced); create a new session"
            )
        fut = self._adopting.get(key)
        if fut is None:
            fut = self._adopting[key] = asyncio.ensure_future(
                self._adopt(s.model, s.model_version, s.fingerprint)
            )
            fut.add_done_callback(lambda _: self._adopting.pop(key, None))
        return await asyncio.shield(fut)

    async def _adopt(self, name: str, version: str, fp: str) -> LoadedModel:
        """Find version `version` (fingerprint `fp`) of model `name` under the checkpoint roots and load it, as a
        draining version: it serves the sessions that need it and is unloaded when none is left here."""
        roots = list(self.settings.checkpoints)
        where = ", ".join(str(r) for r in roots)
        path = await asyncio.to_thread(find_by_fingerprint, roots, version, fp)
        if path is None:
            raise FailedPrecondition(
                f"version {version!r} of model {name!r} is not loaded on this server, and no checkpoint with its "
                f"fingerprint ({fp[:16] or 'unknown'}...) is under the checkpoint roots ({where})"
            )
        async with self._admin:
            m = self.registry.find(name, version)
            if m is not None:
                return m
            try:
                m = await asyncio.to_thread(
                    load_model,
                    name,
                    path,
                    self.settings.naive,
                    fp or None,
                    DRAINING,
                    **self._engine_placement(),
                )
                self.registry.add(m)
            except (CheckpointError, ServiceError) as e:
                msg = e.message if isinstance(e, ServiceError) else str(e)
                raise FailedPrecondition(
                    f"version {version!r} of model {name!r} is not loaded on this server and could not be loaded "
                    f"from {path}: {msg}"
                ) from None
            self._start_batcher(m)
            log.info("model version adopted", extra={"model": name, "version": version, "path": str(path)})
            return m

    # ----- goals --------------------------------------------------------------------------------------------
    @staticmethod
    def resolve_goal(m: LoadedModel, goal: GoalRef, target: float | None) -> int:
        """A goal id from an id, a name, or the nearest goal mean to a target statistic value.

        Raises:
            InvalidArgument: none or both given, unknown id or name, non-finite target.
        """
        goals = m.checkpoint.goals
        names = ", ".join(f"{g.id}={g.name}" for g in goals)
        if goal is not None and target is not None:
            raise InvalidArgument("give either goal (an id or a name) or target, not both")
        if target is not None:
            if isinstance(target, bool) or not isinstance(target, int | float) or not math.isfinite(target):
                raise InvalidArgument(f"target must be a finite number, got {target!r}")
            if (
                abs(target) > MAX_ABS_VALUE
            ):  # a bound the OpenAPI schema can state exactly (no float rounding)
                raise InvalidArgument(f"target must be within [-1e9, 1e9], got {target!r}")
            return min(goals, key=lambda g: (abs(g.mean - target), g.id)).id
        if isinstance(goal, bool):
            raise InvalidArgument(f"goal must be an id or a name, got {goal!r}")
        if isinstance(goal, int | np.integer):
            try:
                m.engine.check_goal(goal)
            except ValueError as e:
                raise InvalidArgument(str(e)) from None
            return int(goal)
        if isinstance(goal, str):
            for g in goals:
                if g.name == goal:
                    return g.id
            raise InvalidArgument(f"unknown goal name {goal!r} for model {m.name!r}; goals are {names}")
        raise InvalidArgument("give a goal (an id or a name) or a target statistic value")

    # ----- sessions -----------------------------------------------------------------------------------------
    def _lock(self, sid: str) -> asyncio.Lock:
        lock = self._locks.get(sid)
        if lock is None:
            lock = self._locks[sid] = asyncio.Lock()
        return lock

    def _dropped(self, sid: str, key: str) -> None:
        """Free what this process holds for a session that is gone (closed, expired or swept), and unload its
        version when it was the last session of a draining one."""
        name, _, version = key.rpartition("@")
        m = self.registry.find(name, version) if self.registry else None
        if m is not None:
            m.engine.forget(sid)
            self._unload_if_drained(m)

    @staticmethod
    def _live(m: LoadedModel, s: Session) -> Context:
        """The session's live context in the model's engine (adopting a stored one, cache rebuilt if needed)."""
        if isinstance(s.ctx, Context):
            return s.ctx
        try:
            s.ctx = m.engine.from_stored(s.ctx, key=s.id)
        except ValueError as e:
            raise FailedPrecondition(f"session {s.id!r} cannot be continued by this server: {e}") from None
        return s.ctx

    def _caller(self) -> keys.Caller:
        return keys.current(bool(self.keyring))

    def _owned(self, s: Session) -> Session:
        """`s`, when the caller may see it; else NotFound, as for an unknown id (`gmt.service.keys`)."""
        if not keys.visible(s.owner, self._caller()):
            raise self.store.unknown(s.id)
        return s

    def _check_serving(self) -> None:
        if self.closing or not self.started:
            raise Unavailable("server is shutting down" if self.closing else "server is starting")

    def _view_session(self, s: Session) -> SessionView:
        ctx = s.ctx
        m = self.registry.find(s.model, s.model_version)
        names = {g.id: g.name for g in m.checkpoint.goals} if m else {}
        return SessionView(
            session_id=s.id,
            model=s.model,
            model_version=s.model_version or (m.version if m else ""),
            goal=int(ctx.goal),
            goal_name=names.get(int(ctx.goal), ""),
            step=int(ctx.step),
            context_size=ctx.size,
            blend_remaining=ctx.blend_remaining,
            blend_from=int(ctx.blend_from),
            action_mode=ctx.action_mode,
            idle_timeout_s=self.settings.idle_timeout_s,
            expires_in_s=max(self.settings.idle_timeout_s - (self.clock() - s.last_used), 0.0),
            context_goals=[] if ctx.goals is None else [int(g) for g in ctx.goals],
            recording=s.ledger.recording,
        )

    async def create_session(
        self,
        model: str | None = None,
        goal: GoalRef = None,
        target: float | None = None,
        seed: int | None = None,
        action_mode: str | None = None,
        session_id: str | None = None,
        version: str | None = None,
        record: bool | None = None,
    ) -> SessionView:
        """A new session on `model` (optional when one model is loaded) pursuing the given goal; it runs one
        version of the model for its whole life.

        Args:
            version: The model version (must be serving); none: the default, or the canary for its share of
                session ids (a hash of the id and the canary version: a retried create gets the same version).
            session_id: The client's own id for the session (else the server draws one). Creating is then
                idempotent: a retry with the same id and parameters answers the session the first call created.
            record: Record the session's episode (True), never (False), or as `--record-share` draws it (None).

        Raises:
            InvalidArgument: bad goal, target, seed, action mode, session id or version.
            NotFound: unknown model or version.
            FailedPrecondition: the named version is draining.
            AlreadyExists: `session_id` names a live session created with other parameters.
            FailedPrecondition: `record` asked of a server without a recordings directory.
            ResourceExhausted: the maximum number of live sessions is reached.
        """
        self._check_serving()
        sid = uuid.uuid4().hex if session_id is None else check_new_session_id(session_id)
        if version is not None:
            check_version(version)
        m = self.registry.for_new_session(model, version, sid)
        g = self.resolve_goal(m, goal, target)
        try:
            mode = m.engine.check_mode(action_mode)
        except ValueError as e:
            raise InvalidArgument(str(e)) from None
        if seed is not None and (isinstance(seed, bool) or not 0 <= seed < 2**63):
            raise InvalidArgument(f"seed must be an integer in [0, 2**63), got {seed!r}")
        if record is not None and not isinstance(record, bool):
            raise InvalidArgument(f"record must be true or false, got {record!r:.40}")
        records = self._records(sid, record)
        request = f"{m.name}|{g}|{seed}|{mode}"  # what a retry must repeat to be answered the same session
        if version:
            request += f"|{version}"
        if records:
            request += "|record"
        given = {"goal": goal} if target is None else {"target": target}
        named = session_id is not None
        return await run_whole(
            self._create(m, sid, g, mode, seed, request, named, records, given),
            # A caller gone with an unnamed session never learns its id: nobody could use or close it.
            undo=None if named else self._roll_back,
        )

    async def _roll_back(self, v: SessionView) -> None:
        """Close a session made for a caller that went away before it was answered."""
        log.info("session rolled back: its creator went away", extra={"session": short_id(v.session_id)})
        await self.close_session(v.session_id)

    def _records(self, sid: str, record: bool | None) -> bool:
        """Whether a new session records: asked, or drawn by `--record-share`.

        Raises:
            FailedPrecondition: asked, and the server has no recordings directory.
        """
        s = self.settings
        if record is None:
            return s.record_dir is not None and record_drawn(sid, s.record_share)
        if record and s.record_dir is None:
            raise FailedPrecondition(
                "this server keeps no recordings: start gmt serve with --record-dir DIR (GMT_RECORD_DIR) to "
                "create sessions with record"
            )
        return record

    async def _create(
        self,
        m: LoadedModel,
        sid: str,
        g: int,
        mode: str,
        seed: int | None,
        request: str,
        named: bool,
        records: bool,
        given: dict,
    ) -> SessionView:
        async with self._lock(sid):
            if named:  # perhaps a retried create: answer the session the first attempt made
                try:
                    return self._view_session(await self._existing(sid, request))
                except NotFound:
                    pass
            now = self.clock()
            ctx = m.engine.new_context(g, mode, seed, key=sid)
            s = Session(
                sid, m.name, ctx, now, now, request, m.version, m.fingerprint, owner=self._caller().name
            )
            if records:
                cfg = m.checkpoint.config
                s.ledger.layout = Layout.of_model(
                    cfg.obs_shape, cfg.is_image, cfg.discrete_actions, cfg.act_dim
                )
                s.ledger.max_steps = self.settings.record_max_steps
            s.ledger.note_goal(0, g, given, 0, "create", now)
            point_of_no_return()
            try:
                await self.store.create(s)
            except AlreadyExists:  # another replica created it meanwhile: this slot was never the session's
                m.engine.forget(sid)
                return self._view_session(await self._existing(sid, request))
            except BaseException:
                m.engine.forget(sid)
                raise
            if not isinstance(self.store, MemorySessionStore):
                # A shared store holds the truth, and a proxy routes the session's acts by its id, usually to
                # another replica: keep no slot here until this replica is asked to act for it.
                s.ctx = s.ctx.to_stored()
                m.engine.forget(sid)
        self.metrics.created(m.name, m.version, s.owner)
        self.metrics.live_sessions.set(await self.store.count())
        log.info("session created", extra={"session": short_id(s.id), "model": m.key, "goal": g})
        return self._view_session(s)

    async def _existing(self, sid: str, request: str) -> Session:
        """The live session `sid` when it was created by the same request (a retried create), else AlreadyExists."""
        s = await self.store.get(sid, hold=False)
        if s.request != request or not keys.visible(s.owner, self._caller()):
            raise AlreadyExists(
                f"session id {sid!r} is taken by a live session created with other parameters (or by another "
                "key); "
                "choose another id, or repeat the first request exactly to get that session"
            )
        return s

    async def get_session(self, sid: str) -> SessionView:
        """Inspect a session (does not count as use for the idle timeout). Raises NotFound / SessionExpired."""
        check_session_id(sid)
        async with self._lock(sid):
            return self._view_session(self._owned(await self.store.get(sid, hold=False)))

    async def list_sessions(self, offset: int = 0, limit: int = 100) -> tuple[int, list[SessionRow]]:
        """The store's live sessions, newest first: (how many there are, the page from `offset`).

        Acts/s and last latency are as of the session's last act (in a shared store, as of the act before).

        Raises:
            InvalidArgument: `offset` is not in 0..`MAX_LIST_OFFSET` or `limit` not in 1..`MAX_LIST_SESSIONS`.
        """
        if isinstance(offset, bool) or not isinstance(offset, int) or not 0 <= offset <= MAX_LIST_OFFSET:
            raise InvalidArgument(f"offset must be an integer in 0..{MAX_LIST_OFFSET}, got {offset!r}")
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= MAX_LIST_SESSIONS:
            raise InvalidArgument(f"limit must be an integer in 1..{MAX_LIST_SESSIONS}, got {limit!r}")
        caller = self._caller()
        shown = None if caller.sees_all else functools.partial(keys.visible, caller=caller)
        total, briefs = await self.store.list_page(offset, limit, shown)
        now, here = self.clock(), self.settings.replica_id
        rows, goal_names = [], {}
        for b in briefs:
            names = goal_names.get(b.model)
            if names is None:
                m = self.registry.models.get(b.model)
                names = goal_names[b.model] = {g.id: g.name for g in m.checkpoint.goals} if m else {}
            a = b.activity
            rows.append(
                SessionRow(
                    session_id=b.session_id,
                    model=b.model,
                    goal=b.goal,
                    goal_name=names.get(b.goal, ""),
                    step=b.step,
                    idle_s=max(now - b.last_used, 0.0),
                    acts_per_s=a.rate(now) if a.count else None,
                    last_latency_ms=None if a.latency_s is None else a.latency_s * 1000.0,
                    served_by=a.by or (here if b.held_here else None),
                )
            )
        return total, rows

    def validate_observation(self, m: LoadedModel, observation: object) -> np.ndarray:
        """The raw observation checked and normalised, once, into what the engine consumes.

        Raises:
            InvalidArgument: wrong size, non-numeric, NaN/Inf, out of range.
        """
        x = to_array(observation)
        try:
            return m.engine.prepare_observation(x)
        except InvalidObservation as e:
            raise InvalidArgument(str(e)) from None

    async def act(
        self, sid: str, observation: object, step: int | None = None, report: Report | None = None
    ) -> ActResult:
        """Append the observation to the session's context and answer the action (batched with others).

        The act is one unit with its stored answer: a caller that gives up (deadline, cancel) does not stop it,
        and its retry with the same `step` waits for it and gets its answer.

        Args:
            sid: Session id.
            observation: The raw observation.
            step: The step the client expects to act at (the index the answer reports; None = don't check).
                A repeat of the last answered step with the same observation returns that answer again without
                stepping (a safe retry).
            report: The client's report on the outcome of the previous action (`records.check_report`), kept
                by a recorded session with this step.

        Raises:
            InvalidArgument: bad observation (the session is unchanged).
            FailedPrecondition: `step` is neither the session's next step nor a repeat of its last one, or it
                repeats the last step with another observation, or a report comes with the first act of an
                episode (it has no previous action).
            NotFound / SessionExpired: no such session.
            Aborted: another replica changed the session meanwhile (retry).
        """
        self._check_serving()
        check_session_id(sid)
        return await run_whole(self._act(sid, observation, step, report))

    async def _act(self, sid: str, observation: object, step: int | None, report: Report | None) -> ActResult:
        t0 = time.perf_counter()
        async with self._lock(sid):
            s, m, ctx, x, repeat = await self._prepare(sid, observation, step, report)
            if repeat is not None:
                return repeat
            step, goal, version = ctx.step, ctx.goal, ctx.version
            try:
                action = await self._batcher(m).act(ctx, x)
            except StepFailed as e:
                raise InvalidArgument(str(e)) from None
            s.last_used = self.clock()
            self._note_step(m, s, ctx, step, observation, action, report)
            await self._save(m, s, version)
            result = self._result(m, sid, action, step, goal)
            self._acted(s, result, t0, report)
        return result

    def _acted(self, s: Session, r: ActResult, t0: float, report: Report | None = None) -> None:
        """Account for an answered act begun at `perf_counter()` `t0`: the session's activity, its watchers (who
        also get the reward the client reported for the previous step, when it did)."""
        latency = time.perf_counter() - t0
        s.activity.record(s.last_used, latency, self.settings.replica_id)
        if s.id in self.events:
            action = r.action if r.action is not None else r.discrete_action
            data = {"step": r.step, "goal": r.goal, "action": action, "latency_ms": latency * 1000.0}
            if report is not None and report.reward is not None:
                data["reward"], data["reward_step"] = report.reward, r.step - 1
            self.events.publish(s.id, "act", data)

    async def _prepare(self, sid: str, observation: object, step: int | None, report: Report | None = None):
        """(session, model, live context, prepared observation, the repeated answer or None) of one act."""
        s = self._owned(await self.store.get(sid))
        m = await self._model_of(s)
        x = self.validate_observation(m, observation)
        ctx = self._live(m, s)
        repeat = self._repeat(m, sid, ctx, step, x)
        if repeat is None and report is not None and ctx.step == 0:
            raise FailedPrecondition(
                "reward, terminated, truncated and info report the outcome of the previous action; the first act "
                "of an episode (step 0) has none: send them with the next act"
            )
        return s, m, ctx, x, repeat

    def _note_step(
        self, m: LoadedModel, s: Session, ctx: Context, t: int, observation, action, report: Report | None
    ) -> None:
        """Record answered step `t` when the session records (and its recording has room)."""
        lg = s.ledger
        if lg.layout is None or lg.recorded >= lg.max_steps:
            return
        raw = to_array(observation).reshape(lg.layout.obs_shape)
        token, goal, w, _, _ = ctx.held(t)
        lg.note_step(t, token, goal, w, s.last_used, raw, action, report)
        if lg.recorded == lg.max_steps:
            log.info("recording stopped", extra={"session": short_id(s.id), "steps": lg.recorded})

    def _repeat(
        self, m: LoadedModel, sid: str, ctx: Context, step: int | None, x: np.ndarray
    ) -> ActResult | None:
        """None when an act for `step` should run; the last answer when it repeats the last answered step.

        Raises:
            InvalidArgument: `step` is not an integer >= 0.
            FailedPrecondition: `step` is neither the session's next step nor its last answered one, or it is the
                last answered one with an observation other than the one answered.
        """
        if step is None or step == ctx.step:
            if step is not None and (isinstance(step, bool) or not isinstance(step, int)):
                raise InvalidArgument(f"step must be an integer >= 0, got {step!r}")
            return None
        if isinstance(step, bool) or not isinstance(step, int) or step < 0:
            raise InvalidArgument(f"step must be an integer >= 0, got {step!r}")
        if step == ctx.step - 1:
            if not m.engine.same_as_last(ctx, x):
                raise FailedPrecondition(
                    f"session {sid!r} already answered step {step} for another observation; a retry must send "
                    f"the same observation (or act at step {ctx.step} with a new one)"
                )
            action, goal = m.engine.last_answer(ctx)
            return self._result(m, sid, action, step, goal)
        accepted = f"only {ctx.step}, or {ctx.step - 1} to repeat the last answer," if ctx.step else "only 0"
        raise FailedPrecondition(
            f"session {sid!r} is at step {ctx.step}; this act is for step {step} ({accepted} is accepted)"
        )

    async def act_many(self, items: list[tuple]) -> list[ActResult | ServiceError]:
        """One step for each (session id, observation[, expected step[, report]]), all in one forward pass.

        A bad item fails alone. A session may appear once per call; a repeat fails as invalid_argument (also
        when its first item failed). An expected step works as in `act`. An observation that is a ServiceError
        (an adapter could not decode it) fails its item with that error. Like `act`, the call runs to its end
        even if its caller gives up.

        Returns:
            In request order: the item's ActResult, or the ServiceError that failed it.

        Raises:
            InvalidArgument: more than MAX_ACT_ITEMS items (the whole call fails).
        """
        if len(items) > MAX_ACT_ITEMS:
            raise InvalidArgument(
                f"a call may act for at most {MAX_ACT_ITEMS} sessions, got {len(items)} requests"
            )
        self._check_serving()
        return await run_whole(self._act_many(items))

    async def _act_many(self, items: list[tuple]) -> list[ActResult | ServiceError]:
        t0 = time.perf_counter()
        out: list[ActResult | ServiceError | None] = [None] * len(items)
        seen: set[str] = set()
        order: list[int] = []
        for i, (sid, *_) in enumerate(items):
            try:
                check_session_id(sid)
            except ServiceError as e:  # the id is not quoted: the item names its index
                out[i] = type(e)(f"item {i}: {e.message}")
                continue
            if sid in seen:
                out[i] = InvalidArgument(f"session {sid!r} appears more than once in this call")
            else:
                seen.add(sid)
                order.append(i)
        order.sort(key=lambda i: items[i][0])  # locks in one global order: two calls never deadlock
        async with contextlib.AsyncExitStack() as stack:
            ready: list[tuple[int, Session, LoadedModel, Context, np.ndarray, object, Report | None]] = []
            for i in order:
                sid, observation, step, report = (*items[i], None, None)[:4]
                if isinstance(observation, ServiceError):
                    out[i] = observation
                    continue
                await stack.enter_async_context(self._lock(sid))
                try:
                    s, m, ctx, x, repeat = await self._prepare(sid, observation, step, report)
                    if repeat is not None:
                        out[i] = repeat
                        continue
                    ready.append((i, s, m, ctx, x, observation, report))
                except ServiceError as e:
                    out[i] = e
            by_model: dict[str, list] = {}
            for r in ready:
                by_model.setdefault(r[2].key, []).append(r)
            for rows in by_model.values():
                steps = [(r[3].step, r[3].goal, r[3].version) for r in rows]
                actions = await self._batcher(rows[0][2]).act_many([r[3] for r in rows], [r[4] for r in rows])
                now = self.clock()
                stepped = []
                for (i, s, m, ctx, _, obs, report), (step, goal, version), a in zip(
                    rows, steps, actions, strict=True
                ):
                    if isinstance(a, StepFailed):
                        out[i] = InvalidArgument(str(a))
                        continue
                    if isinstance(a, BaseException):
                        raise a
                    s.last_used = now
                    self._note_step(m, s, ctx, step, obs, a, report)
                    stepped.append((i, s, m, version, self._result(m, s.id, a, step, goal), report))
                # Every write at once: a shared store sends them in one round trip (group commit).
                point_of_no_return()
                saved = await self.store.save_many([(s, version) for _, s, _, version, _, _ in stepped])
                for (i, s, m, _, result, report), e in zip(stepped, saved, strict=True):
                    if e is not None:
                        m.engine.forget(s.id)  # the store holds the truth now: adopt it afresh next time
                    else:
                        self._acted(s, result, t0, report)
                    out[i] = e if e is not None else result
        return out

    async def _save(self, m: LoadedModel, s: Session, read_version: int) -> None:
        """Write the session back (compare-and-set on the version read); a lost race drops this replica's copy."""
        point_of_no_return()
        try:
            await self.store.save(s, read_version)
        except ServiceError:
            m.engine.forget(s.id)  # the store holds the truth now: adopt it afresh on the next request
            raise

    @staticmethod
    def _result(m: LoadedModel, sid: str, action, step: int, goal: int) -> ActResult:
        if m.checkpoint.config.discrete_actions:
            return ActResult(sid, None, int(action), step, goal)
        return ActResult(sid, np.asarray(action, dtype=np.float32).tolist(), None, step, goal)

    async def set_goal(
        self,
        sid: str,
        goal: GoalRef = None,
        target: float | None = None,
        blend_steps: int = 0,
        by: str = "rest",
    ) -> SessionView:
        """Condition the session's next steps on a new goal, optionally fading it in over `blend_steps` steps.

        The change joins the session's timeline; the answer's `effective_step` is the step of the first act that
        uses it. A change that repeats the timeline's last entry (same step, goal as given, blend) is a retry: it
        changes nothing and is answered the same.

        Args:
            by: Who asks (`records.BY`: rest, grpc or stream), as the timeline lists it.

        Raises:
            InvalidArgument: bad goal, target or blend_steps.
            NotFound / SessionExpired: no such session.
        """
        self._check_serving()
        check_session_id(sid)
        try:  # before the session is read: a bad value is refused whatever the session's state
            check_blend_steps(blend_steps)
        except ValueError as e:
            raise InvalidArgument(str(e)) from None
        if by not in BY:
            raise ValueError(f"by must be one of {BY}, got {by!r}")
        return await run_whole(self._set_goal(sid, goal, target, blend_steps, by))

    async def _set_goal(
        self, sid: str, goal: GoalRef, target: float | None, blend_steps: int, by: str
    ) -> SessionView:
        async with self._lock(sid):
            s = self._owned(await self.store.get(sid))
            m = await self._model_of(s)
            g = self.resolve_goal(m, goal, target)
            ctx = self._live(m, s)
            step, now = ctx.step, self.clock()
            given = {"goal": goal} if target is None else {"target": target}
            if not s.ledger.note_goal(step, g, given, blend_steps, by, now):
                return dataclasses.replace(self._view_session(s), effective_step=step)  # a retry: as it was
            version = ctx.version
            if n := m.engine.set_goal(ctx, g, blend_steps):
                s.relabelled_from = min(step - n, step if s.relabelled_from is None else s.relabelled_from)
            s.last_used = now
            await self._save(m, s, version)
            log.info("goal set", extra={"session": short_id(sid), "goal": g, "blend_steps": blend_steps})
            view = dataclasses.replace(self._view_session(s), effective_step=step)
            if sid in self.events:
                data = {"goal": g, "goal_name": view.goal_name, "step": view.step, "given": given}
                self.events.publish(sid, "goal", {**data, "blend_steps": blend_steps})
            return view

    async def reset(self, sid: str, goal: GoalRef = None, target: float | None = None) -> SessionView:
        """Start a new episode in the session, keeping its goal unless one is given.

        Raises:
            InvalidArgument: bad goal or target.
            NotFound / SessionExpired: no such session.
        """
        self._check_serving()
        check_session_id(sid)
        return await run_whole(self._reset(sid, goal, target))

    async def _reset(self, sid: str, goal: GoalRef, target: float | None) -> SessionView:
        async with self._lock(sid):
            s = self._owned(await self.store.get(sid))
            m = await self._model_of(s)
            g = None if goal is None and target is None else self.resolve_goal(m, goal, target)
            ctx = self._live(m, s)
            lg, now = s.ledger, self.clock()
            last = lg.last
            if (
                ctx.step == 0
                and last is not None
                and last["episode"] == lg.episode
                and last["by"] in ("create", "reset")
                and (g is None or g == ctx.goal)
            ):
                return self._view_session(s)  # an episode not begun: a reset (or its retry) changes nothing
            version = ctx.version
            m.engine.reset(ctx, g)
            lg.episode += 1
            given = {} if g is None else {"goal": goal} if target is None else {"target": target}
            lg.note_goal(0, int(ctx.goal), given, 0, "reset", now)
            s.last_used = now
            await self._save(m, s, version)
            view = self._view_session(s)
            if sid in self.events:
                self.events.publish(sid, "reset", {"goal": view.goal, "goal_name": view.goal_name, "step": 0})
            return view

    async def close_session(self, sid: str) -> None:
        """Forget the session. Raises NotFound / SessionExpired."""
        check_session_id(sid)
        await run_whole(self._close(sid))

    async def _close(self, sid: str) -> None:
        async with self._lock(sid):
            point_of_no_return()
            s = self._owned(await self.store.get(sid, hold=False))
            if not s.ledger.recording:
                await self.store.delete(sid)
            else:
                await self._close_recorded(sid)
            self.events.end(sid, "closed", {"session_id": sid})
        self.metrics.live_sessions.set(await self.store.count())
        log.info("session closed", extra={"session": short_id(sid)})

    async def _close_recorded(self, sid: str, attempts: int = 3) -> None:
        """Write a recorded session's recording, then remove the session if nothing changed it meanwhile (another
        replica acting in between is written again: never a step lost, never one twice in the file).

        Raises:
            Aborted: it kept changing for `attempts` snapshots (retry the close).
        """
        for _ in range(attempts):
            s, timeline, records = await self.store.entries(sid, records=True)
            if self.settings.record_dir is None:
                log.warning(
                    "recorded session closed on a server without --record-dir: its recording is dropped",
                    extra={"session": short_id(sid), "steps": len(records)},
                )
            else:
                await self._archive(s, timeline, records, "close")
            try:
                await self.store.delete(sid, read=s)
                return
            except Aborted:
                continue
        raise Aborted(f"session {sid!r} kept changing while it was being closed; retry the close")

    # ----- records ------------------------------------------------------------------------------------------
    def _describe(self, s: Session, ended_by: str | None) -> dict:
        """A recording's metadata (`gmt.common.recording`) for session `s`."""
        m = self.registry.find(s.model, s.model_version) if self.registry else None
        c = m.checkpoint if m is not None else None
        return {
            "session_id": s.id,
            "model": s.model,
            "model_version": s.model_version or (m.version if m else None),
            "fingerprint": s.fingerprint or (m.fingerprint if m else None),
            "env_id": c.env_id if c else None,
            "observation_space": c.observation_space if c else None,
            "action_space": c.action_space if c else None,
            "statistic": c.statistic if c else None,
            "goals": [dataclasses.asdict(g) for g in c.goals] if c else None,
            "action_mode": s.ctx.action_mode,
            "seed": int(s.ctx.seed),
            "created_at": s.created_at,
            "ended_at": None if ended_by is None else self.clock(),
            "ended_by": ended_by,
            "max_steps": s.ledger.max_steps,
            "stopped": s.ledger.stopped,
        }

    def _assemble(
        self, s: Session, timeline: list[bytes], records: list[bytes], ended_by: str | None
    ) -> Recording:
        return assemble(self._describe(s, ended_by), s.ledger.layout, timeline, records)

    async def _archive(self, s: Session, timeline: list[bytes], records: list[bytes], ended_by: str) -> None:
        """Write the recording of `s` into the recordings directory (assembled and written in a thread)."""
        meta = self._describe(s, ended_by)
        directory = self.settings.record_dir

        def write() -> Path:
            return assemble(meta, s.ledger.layout, timeline, records).write(directory)

        path = await asyncio.to_thread(write)
        log.info(
            "recording written",
            extra={"session": short_id(s.id), "steps": len(records), "path": str(path), "ended_by": ended_by},
        )

    def _archive_soon(
        self, s: Session, timeline: list[bytes], records: list[bytes], ended_by: str
    ) -> asyncio.Task:
        task = asyncio.get_running_loop().create_task(self._archive(s, timeline, records, ended_by))
        self._archives.add(task)
        task.add_done_callback(self._archived)
        return task

    def _archived(self, task: asyncio.Task) -> None:
        self._archives.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("a recording could not be written", exc_info=task.exception())

    def _expiring(self, s: Session, timeline: list[bytes], records: list[bytes]) -> asyncio.Task | None:
        """The store's `on_expire`: write the recording of a recorded session that expires."""
        if self.settings.record_dir is None:
            log.warning(
                "recorded session expired on a server without --record-dir: its recording is dropped",
                extra={"session": short_id(s.id), "steps": len(records)},
            )
            return None
        return self._archive_soon(s, timeline, records, "expiry")

    async def timeline(self, sid: str, offset: int = 0, limit: int = MAX_TIMELINE_PAGE) -> TimelineView:
        """A page of every goal the session had: `limit` entries from the `offset`-th, decoded in a worker thread.

        Raises:
            InvalidArgument: offset or limit out of range.
            NotFound / SessionExpired: no such session.
        """
        check_session_id(sid)
        if not 0 <= offset <= MAX_LIST_OFFSET:
            raise InvalidArgument(f"offset must be in [0, {MAX_LIST_OFFSET}], got {offset}")
        if not 1 <= limit <= MAX_TIMELINE_PAGE:
            raise InvalidArgument(f"limit must be in [1, {MAX_TIMELINE_PAGE}], got {limit}")
        async with self._lock(sid):
            s, timeline, _ = await self.store.entries(sid, records=False, page=(offset, limit))
            self._owned(s)
        m = self.registry.find(s.model, s.model_version)
        goals = await asyncio.to_thread(decode_timeline, timeline)
        return TimelineView(
            session_id=s.id,
            model=s.model,
            model_version=s.model_version or (m.version if m else ""),
            fingerprint=s.fingerprint or (m.fingerprint if m else None),
            step=int(s.ctx.step),
            episode=s.ledger.episode,
            goals=goals,
            entries=s.ledger.entries,
            offset=offset,
        )

    async def recording(self, sid: str) -> Recording:
        """The session's recording so far (it stays live).

        Raises:
            NotFound: no such session, or it does not record.
        """
        check_session_id(sid)
        async with self._lock(sid):
            s, timeline, records = await self.store.entries(sid, records=True)
            self._owned(s)
        if not s.ledger.recording:
            raise NotFound(
                f"session {sid!r} has no recording: it was created without record (POST /sessions with "
                '"record": true, on a server with --record-dir)'
            )
        return await asyncio.to_thread(self._assemble, s, timeline, records, None)
