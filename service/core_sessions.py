"""The core's session calls: create (idempotent under a client's id), inspect, list, change the goal, reset and
close, each under the session's lock (`gmt.service.ids.SessionLocks`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import uuid

import numpy as np

from gmt.model.context import Context
from gmt.model.engine import check_blend_steps
from gmt.service import keys
from gmt.service.activity import SessionRow
from gmt.service.core_state import CoreState
from gmt.service.errors import AlreadyExists, FailedPrecondition, InvalidArgument, NotFound
from gmt.service.ids import check_new_session_id, check_session_id, check_version, short_id
from gmt.service.observations import MAX_ABS_VALUE
from gmt.service.records import BY, Layout
from gmt.service.registry import LoadedModel
from gmt.service.sessions import MemorySessionStore, Session
from gmt.service.units import point_of_no_return, run_whole
from gmt.service.views import MAX_LIST_OFFSET, MAX_LIST_SESSIONS, GoalRef, SessionView

log = logging.getLogger("gmt.core")


class Sessions(CoreState):
    """Session calls, a part of `gmt.service.core.Core`."""

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

    @staticmethod
    def _live(m: LoadedModel, s: Session) -> Context:
        """The session's live context in the model's engine (adopting a stored one, cache rebuilt if needed; a live
        one of an engine that is gone, as after its version was unloaded with force and loaded again, is carried
        over the same way: never read through another pool's slot)."""
        if isinstance(s.ctx, Context):
            if s.ctx.pool is m.engine.pool:
                return s.ctx
            s.ctx = s.ctx.to_stored()
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
        await self._count_live()
        owned = {"key": s.owner} if s.owner else {}  # the key's name, never its token
        log.info("session created", extra={"session": short_id(s.id), "model": m.key, "goal": g, **owned})
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
            self._goal_set(view, g, given, blend_steps)
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
            self._was_reset(view)
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
            self._ended(sid, "closed")
        await self._count_live()
        log.info("session closed", extra={"session": short_id(sid)})
