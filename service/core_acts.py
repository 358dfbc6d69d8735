"""The core's act path: one session's act, and many sessions' acts in one forward pass, each with its stored
answer (a retry of the last step is answered again), written back with compare-and-set.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time

import numpy as np

from gmt.model.context import Context
from gmt.model.engine import InvalidObservation, StepFailed
from gmt.service.core_state import CoreState
from gmt.service.errors import FailedPrecondition, InvalidArgument, ServiceError
from gmt.service.ids import check_session_id, short_id
from gmt.service.observations import to_array
from gmt.service.records import Report
from gmt.service.registry import LoadedModel
from gmt.service.sessions import Session
from gmt.service.units import point_of_no_return, run_whole
from gmt.service.views import MAX_ACT_ITEMS, ActResult

log = logging.getLogger("gmt.core")


class Acts(CoreState):
    """The act path, a part of `gmt.service.core.Core`."""

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
            by_model: dict[int, list] = {}  # by the loaded version itself (one engine a pass), not its key
            for r in ready:
                by_model.setdefault(id(r[2]), []).append(r)
            for rows in by_model.values():
                await self._act_rows(rows, out, t0)
        return out

    async def _act_rows(self, rows: list[tuple], out: list, t0: float) -> None:
        """One model's rows of an `act_many` call: their forward pass, then their answers and writes.

        A call of many rows goes in two parts (`MicroBatcher.call_cut`), each in a pass of its own: the first part
        is answered and written while the engine runs the second (the event loop and the store wait on the engine
        no more than one part's time), and the second's write follows as soon as its pass is done, whether or not
        the first's is acknowledged yet.
        """
        batcher = self._batcher(rows[0][2])
        steps = [(r[3].step, r[3].goal, r[3].version) for r in rows]  # before the engine advances them
        cut = batcher.call_cut(len(rows))
        parts = [(rows[lo:hi], steps[lo:hi]) for lo, hi in ((0, cut), (cut, len(rows))) if lo < hi]
        passes = [
            asyncio.ensure_future(batcher.act_many([r[3] for r in p], [r[4] for r in p], solo=len(parts) > 1))
            for p, _ in parts
        ]
        # (part, its answers and write) for each part whose pass ran
        answers: list[tuple[int, asyncio.Future]] = []
        failed: list[BaseException | None] = [None] * len(parts)
        try:
            for k, ((part, part_steps), forward) in enumerate(zip(parts, passes, strict=True)):
                try:
                    actions = await forward
                except Exception as e:  # noqa: BLE001 - its pass failed as a whole
                    # The other part (which may have run already) is still answered and written; then the call fails.
                    failed[k] = e
                    continue
                # Its write goes while the next part's pass runs, not after the write before it is acknowledged.
                answers.append(
                    (k, asyncio.ensure_future(self._answer_rows(part, part_steps, actions, out, t0)))
                )
        except BaseException:  # cancelled: only while no pass has started (`units`), so neither may run later
            for forward in passes:
                forward.cancel()
            raise
        finally:  # no pass, no write may outlive the call (its sessions' locks)
            done = await asyncio.gather(*passes, *(a for _, a in answers), return_exceptions=True)
        for (k, _), e in zip(answers, done[len(passes) :], strict=True):
            if isinstance(e, BaseException):
                failed[k] = e
        first = next((e for e in failed if e is not None), None)
        if first is not None:
            raise first

    async def _answer_rows(
        self, rows: list[tuple], steps: list[tuple], actions: list, out: list, t0: float
    ) -> None:
        """Note the rows' steps and write them back (one group commit); their answers (or errors) into `out`."""
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
