"""Cross-session micro-batching: concurrent `act` calls on one model share one forward pass.

A batch waits (at most `max_wait_s` after its first request) only for the sessions that are acting: those answered
within the last `active_window_s` (a session has at most one request in flight, so one of them not queued may be
on its way). An idle session, one that never acted or stopped acting, is never waited for, so idle neighbours cost
an acting session nothing; with none acting beside it, a request runs as soon as the engine is free, with what
arrived while it was busy. A batch closes when it holds `max_batch` requests, when every acting session has a
request queued, or at the deadline. When many sessions act one at a time (`SPLIT_FROM` or more), a pass takes at
most half of them (a quarter with a remote store, `parts`): the event loop then parses and answers one part while
the engine runs another.
The forward runs in a worker thread so that the event loop keeps serving (a lone session's may run on the loop,
see `inline_alone`).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from gmt.model.context import Context
from gmt.model.engine import PolicyEngine
from gmt.service import units
from gmt.service.errors import Unavailable

log = logging.getLogger("gmt.batcher")

ACTIVE_S = 1.0  # a session answered within this long (or twice the batch wait, if longer) counts as acting
# From this many sessions acting one at a time, a pass takes at most half of them (rounded up), so that the loop's
# work for one half overlaps the engine's for the other. On 2 cores, 256 sessions over REST at max_batch 256:
# 4,476-4,890 acts/s in whole passes, 6,080-6,353 in halves (docs/performance.md).
SPLIT_FROM = 64
# With a store whose writes wait for another process (Redis, `SessionStore.remote`), a pass takes at most a quarter,
# but no fewer than SPLIT_FROM (nor more than half): while one pass's write waits for its acknowledgement (and the
# replica's, with WAIT), the loop works on the others instead of running dry. Over REST with the store as `make
# cluster` deploys it, against memory in the same runs (4 rounds each): at 256 sessions 0.752-0.782x in quarters
# (64 a pass), 0.670-0.699x in halves (three runs), thirds 0.71x, fifths, sixths and eighths 0.72-0.75x; at 128
# sessions halves (64) 0.718x, quarters (32) 0.676x; at 64 halves (32) 0.652x, quarters (16) 0.624x. In memory,
# quarters and halves are the same at 256 (0.987x; docs/performance.md).
REMOTE_STORE_PARTS = 4
# How long a closing batcher waits for a pass already running in its thread to end (then answers it); a pass still
# running after that is given up: its callers fail as unavailable (a device that hangs must not hang an unload).
CLOSE_PASS_S = 30.0
# A many-session call of at most this many rows runs right on the event loop when `inline_alone` would run a lone
# act there (nothing queued or running, no session acting one at a time): ~0.5 ms of the loop at most.
INLINE_ROWS = 8


@dataclass
class _Item:
    ctx: Context
    obs: np.ndarray
    future: asyncio.Future | None
    group: int = 0  # items of one many-session call (> 0) go through one forward pass together
    solo: bool = False  # its group runs in a pass of its own (a part of a call split in two)
    unit: units.Unit | None = None  # the change it belongs to: no longer cancellable once its forward starts


def _key(ctx: Context | object) -> object:
    """The session an item belongs to: its pool slot (a session has at most one request in flight)."""
    return getattr(ctx, "slot", ctx)


class MicroBatcher:
    """Collects (context, observation) pairs for one engine and answers them in batches.

    Args:
        engine: The model's engine.
        executor: Runs `engine.act` off the event loop (None: on the loop itself, for the naive server).
        max_batch: Most requests in one forward pass.
        max_wait_s: Longest time the first request of a batch waits for the acting sessions not yet queued.
        observe: Called with (batch size, forward seconds) after every forward pass.
        inline_alone: When nothing is queued or running and no other session is acting, run an act (or a
            many-session call of at most `INLINE_ROWS` rows) right away on the event loop: a lone session then
            pays no queue, batching task or thread hop (~0.3 ms here). For engines whose step is short (the
            native kernel: ~0.1 ms per session), so the loop is never held long.
        clock: Monotonic seconds, for the acting window.
        call_threads: Threads the engine may split a pass of a many-session call between (`PolicyEngine.act`'s
            `threads`); passes of single acts get one.
        parts: From `SPLIT_FROM` sessions acting one at a time, a pass takes at most this share of them, but no
            fewer than `SPLIT_FROM` nor more than half (2: half; `REMOTE_STORE_PARTS` when the session store's
            writes wait for another process).

    Attributes:
        active_window_s: How long after its last answer a session counts as acting: `ACTIVE_S`, or twice
            `max_wait_s` if that is longer.
        waits: Batches that waited for an acting session (instrumentation: idle sessions never add to it).
        split: Whether a pass takes at most half of the acting sessions when `SPLIT_FROM` or more act (True
            when the forward runs off the loop, on `executor`; with none, nothing would overlap it).
    """

    def __init__(
        self,
        engine: PolicyEngine,
        executor: Executor | None,
        max_batch: int,
        max_wait_s: float,
        observe: Callable[[int, float], None] | None = None,
        inline_alone: bool = False,
        clock: Callable[[], float] = time.monotonic,
        call_threads: int = 1,
        parts: int = 2,
    ) -> None:
        self.engine = engine
        self.executor = executor
        self.max_batch = max_batch
        self.max_wait_s = max_wait_s
        self.observe = observe
        self.inline_alone = inline_alone
        self.clock = clock
        self.call_threads = call_threads
        if parts < 1:
            raise ValueError(f"parts must be >= 1, got {parts}")
        self.parts = parts
        self._pending: collections.deque[_Item] = collections.deque()
        self._wake = asyncio.Event()
        self._task: asyncio.Task | None = None
        self._running: list[_Item] = []
        self._groups = 0
        self.active_window_s = max(ACTIVE_S, 2 * max_wait_s)
        # Sessions that acted one at a time, by `_key`: loop time of their last answer, oldest first.
        self._active: dict[object, float] = {}
        self._missing: set = set()  # acting sessions the batch being gathered still waits for
        self.waits = 0
        self.split = executor is not None
        self._closing = False  # close() has begun: a crash then ends the loop instead of restarting it

    def start(self) -> None:
        """Start the (supervised) batching task on the running loop."""
        self.restarts = 0
        self._task = asyncio.get_running_loop().create_task(self._supervise(), name="micro-batcher")

    @property
    def healthy(self) -> bool:
        """Whether the batching task runs."""
        return self._task is not None and not self._task.done()

    async def _supervise(self) -> None:
        """Run the batching loop; if it ever crashes, fail only the calls it held (`Unavailable`) and restart."""
        while True:
            try:
                await self._run()
            except asyncio.CancelledError:
                raise
            except Exception as e:  # noqa: BLE001 - a bug in the loop must not strand its callers
                log.exception(
                    "batcher crashed; restarting" if not self._closing else "batcher crashed while closing"
                )
                self.restarts += 1
                self._fail_held(Unavailable(f"the batcher failed ({type(e).__name__}); retry the request"))
                if self._closing:  # its cancellation was spent finishing the last pass: stop, do not restart
                    return

    @property
    def idle(self) -> bool:
        """Whether no request waits or runs."""
        return not self._running and not self._live()

    async def close(self, wait_s: float = 0.0) -> None:
        """Stop batching, after the queued requests are answered if that takes at most `wait_s`. A pass already
        running is finished and answered (its callers are past their point of no return), if it ends within
        `CLOSE_PASS_S`; requests still queued then (and those of a pass that did not end) fail as unavailable."""
        self._closing = True
        deadline = time.monotonic() + wait_s
        while not self.idle and time.monotonic() < deadline and self.healthy:
            await asyncio.sleep(0.005)
        if self._task is not None:
            self._task.cancel()
            # Not `gather`: a caller of close() that is cancelled itself must not cancel the task again.
            await asyncio.wait({self._task}, timeout=CLOSE_PASS_S)
        self._fail_held(
            Unavailable("this model version stopped serving here before the request ran; retry it")
        )

    def _fail_held(self, error: Unavailable) -> None:
        """Fail every request held here, running or queued, that is not answered yet; hold none after."""
        for item in [*self._running, *self._pending]:
            if not item.future.done():
                item.future.set_exception(error)
        self._running = []
        self._pending.clear()

    async def act(self, ctx: Context, obs: np.ndarray) -> np.ndarray | int:
        """The action for one prepared observation (`engine.prepare_observation`); `ctx` is advanced by the engine.

        Raises the item's own error (an engine `StepFailed`) when its row alone failed.

        Cancelling the caller before the batch runs drops the request. Once it runs, its change is past its point
        of no return (`gmt.service.units`): the core lets it finish and store its answer.
        """
        if self._task is None or self._task.done():
            raise RuntimeError("batcher is not running")
        loop = asyncio.get_running_loop()
        key = _key(ctx)
        if self._may_run_here(key):
            (action,) = self._run_here([ctx], [obs])
            if isinstance(action, Exception):
                raise action
            self._answered(key, self.clock())
            return action
        fut = loop.create_future()
        self._pending.append(_Item(ctx, obs, fut, unit=units.current()))
        self._missing.discard(key)
        self._wake.set()
        return await fut

    def _answered(self, key: object, now: float) -> None:
        self._active.pop(key, None)
        self._active[key] = now  # the most recent last

    def _acting(self, now: float, exclude: object = None) -> set:
        """Acting sessions (answered within `active_window_s`) other than `exclude` and those queued; sessions
        answered longer ago are forgotten until they act again."""
        active, oldest = self._active, now - self.active_window_s
        while active:
            key = next(iter(active))
            if active[key] >= oldest:
                break
            del active[key]
        acting = set(active)
        acting.discard(exclude)
        if acting:
            acting.difference_update(_key(it.ctx) for it in self._pending)
        return acting

    async def act_many(self, ctxs: list[Context], obs: list[np.ndarray], solo: bool = False) -> list:
        """Actions for many sessions at once, in one forward pass (never split by `max_batch`).

        Args:
            ctxs: The sessions' contexts.
            obs: Their prepared observations.
            solo: Run them in a pass of their own, with no other request (for the parts of one call that is
                answered part by part while the engine runs the next part).

        Returns per item the action or the exception that failed that item alone.
        """
        if self._task is None or self._task.done():
            raise RuntimeError("batcher is not running")
        if not solo and len(ctxs) <= INLINE_ROWS and self._may_run_here():
            return self._run_here(ctxs, obs)
        loop = asyncio.get_running_loop()
        self._groups += 1
        unit = units.current()
        items = [
            _Item(c, o, loop.create_future(), self._groups, solo=solo, unit=unit)
            for c, o in zip(ctxs, obs, strict=True)
        ]
        self._pending.extend(items)
        self._wake.set()
        return await asyncio.gather(*(it.future for it in items), return_exceptions=True)

    def _may_run_here(self, exclude: object = None) -> bool:
        """Whether a pass may run right here on the loop (`inline_alone`): nothing queued or running, and no session
        but `exclude` acting one at a time (none that a batch would wait for)."""
        return (
            self.inline_alone
            and not self._pending
            and not self._running
            and not self._acting(self.clock(), exclude)
        )

    def _run_here(self, ctxs: list[Context], obs: list[np.ndarray]) -> list:
        """A lone act's or a small call's pass, run right here on the loop: no queue, no batching task, no thread
        hop. Returns per row the action or the exception that failed it (the whole pass's, if it failed)."""
        units.point_of_no_return(units.current())  # its forward runs now: its caller can no longer cancel
        t0 = time.perf_counter()
        self._running = [_Item(c, o, None) for c, o in zip(ctxs, obs, strict=True)]
        try:
            actions = self.engine.act(ctxs, obs, True)
        except Exception as e:  # noqa: BLE001 - the whole pass failed: every row gets its error
            return [e] * len(ctxs)
        finally:
            self._running = []
        if self.observe is not None:
            self.observe(len(ctxs), time.perf_counter() - t0)
        return list(actions)

    @property
    def queued(self) -> int:
        """Requests waiting for a forward pass (not yet running, not cancelled)."""
        return sum(1 for it in self._pending if not it.future.done())

    def _live(self) -> int:
        while self._pending and self._pending[0].future.done():
            self._pending.popleft()
        return self.queued

    def call_cut(self, rows: int) -> int:
        """Where a many-session call of `rows` rows is cut into the two parts it runs in (`act_many(solo=True)`;
        the first part is answered while the engine runs the second): half way from `SPLIT_FROM` rows when the
        forward runs off the loop, else `rows` (one part)."""
        return (rows + 1) // 2 if self.split and rows >= SPLIT_FROM else rows

    def _cap(self) -> int:
        """Most single-session requests in the next pass: `max_batch`, or the acting sessions' share if fewer:
        half of them, or with `parts` > 2 that part of them but no fewer than `SPLIT_FROM` (nor more than half)."""
        acting = len(self._active)
        if not self.split or acting < SPLIT_FROM:
            return self.max_batch
        half = -(-acting // 2)
        return min(self.max_batch, half, max(SPLIT_FROM, -(-acting // self.parts)))

    async def _gather(self, cap: int) -> None:
        """Wait (up to `max_wait_s`) for the acting sessions that have no request queued, until `cap` are queued;
        none missing, or a solo group first in line (which none of them could join): return at once."""
        loop = asyncio.get_running_loop()
        now = loop.time()
        n = self._live()
        if n == 0 or n >= cap or self.max_wait_s <= 0 or not self._active or self._pending[0].solo:
            return
        self._missing = self._acting(self.clock())
        if not self._missing:
            return
        self.waits += 1
        deadline = now + self.max_wait_s
        try:
            while self._missing and self._live() < cap:
                remaining = deadline - loop.time()
                if remaining <= 0:
                    return
                self._wake.clear()
                try:
                    async with asyncio.timeout(remaining):
                        await self._wake.wait()
                except TimeoutError:
                    return
        finally:
            self._missing = set()

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            if not self._live():
                self._wake.clear()
                await self._wake.wait()
                continue
            cap = self._cap()
            await self._gather(cap)
            batch: list[_Item] = []
            while self._pending:
                item = self._pending[0]
                if batch:
                    last = batch[-1]
                    if not (last.group and item.group == last.group) and (
                        len(batch) >= cap or last.solo or item.solo
                    ):
                        break
                self._pending.popleft()
                if item.future.done():
                    continue
                if item.unit is not None and item.unit.dropped:  # its caller gave up: it never runs
                    item.future.cancel()
                    continue
                units.point_of_no_return(item.unit)  # its forward runs now: its caller can no longer cancel
                batch.append(item)
            if not batch:
                continue
            t0 = time.perf_counter()
            self._running = batch
            ctxs, obs = [it.ctx for it in batch], [it.obs for it in batch]
            closing: asyncio.CancelledError | None = None
            try:
                if self.executor is None:
                    actions = self.engine.act(ctxs, obs, True)
                else:
                    threads = self.call_threads if batch[0].group else 1
                    work = loop.run_in_executor(self.executor, self.engine.act, ctxs, obs, True, threads)
                    while True:
                        try:
                            actions = await asyncio.shield(work)
                            break
                        except asyncio.CancelledError as e:
                            # Closed while the pass runs in its thread: its callers are past their point of no
                            # return, so it is finished and answered first (however often the batcher is
                            # cancelled meanwhile); the batcher stops after.
                            if work.cancelled():
                                raise
                            closing = closing or e
            except Exception as e:  # noqa: BLE001 - handed to every caller of the batch
                self._running = []
                for it in batch:
                    if not it.future.done():
                        it.future.set_exception(e)
                if closing is not None:
                    raise closing from None
                continue
            # The batch stays `_running` until it is answered: should answering fail, the supervisor fails its callers.
            if self.observe is not None:
                self.observe(len(batch), time.perf_counter() - t0)
            now = self.clock()
            for it, a in zip(batch, actions, strict=True):
                if not it.group:
                    self._answered(_key(it.ctx), now)
                if it.future.done():
                    continue
                if isinstance(a, Exception):
                    it.future.set_exception(a)
                else:
                    it.future.set_result(a)
            self._running = []
            if closing is not None:
                raise closing
