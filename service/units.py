"""A session change as one unit: it either never happened or completes, whatever its caller does.

A caller that gives up (a gRPC deadline, a cancelled call) cancels the change only while nothing of it is applied
yet: before its forward pass starts, before its write is sent. Past that point of no return the change runs to
its end, stored, holding its session's lock, so that a retry finds it made instead of racing it. The core runs
every change through `run_whole`; the code that applies a change calls `point_of_no_return` first.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import types
from collections.abc import Awaitable, Callable, Coroutine
from typing import TypeVar

T = TypeVar("T")
log = logging.getLogger("gmt.units")


class Unit:
    """One change in flight. `cancellable` turns False at its point of no return and never back; `dropped` turns True
    when its caller gave up before that point (the change is being cancelled: nothing queued for it may start, even
    in the turns of the loop before the cancellation reaches every part of it)."""

    __slots__ = ("cancellable", "dropped")

    def __init__(self) -> None:
        self.cancellable = True
        self.dropped = False


_CURRENT: contextvars.ContextVar[Unit | None] = contextvars.ContextVar("gmt_unit", default=None)
_orphans: set[asyncio.Task] = set()  # changes whose caller went away, running to their end


def current() -> Unit | None:
    """The unit of the running change (None outside one)."""
    return _CURRENT.get()


def point_of_no_return(unit: Unit | None = None) -> None:
    """From here on the change (`unit`, default the running one) completes even if its caller gives up."""
    unit = unit or _CURRENT.get()
    if unit is not None:
        unit.cancellable = False


async def run_whole(work: Awaitable[T], undo: Callable[[T], Awaitable[object]] | None = None) -> T:
    """Await `work` as one unit (see the module docstring).

    Args:
        undo: For a change nobody can use unless its caller hears of it (an unnamed create): awaited with the
            change's result when the caller gave up past the point of no return, so that it is rolled back.

    Raises:
        asyncio.CancelledError: the caller was cancelled (the change was then dropped if nothing of it was
            applied, else it goes on in the background).
    """
    unit = Unit()
    token = _CURRENT.set(unit)
    try:
        if isinstance(work, types.CoroutineType):
            # Its first step runs here, as an eager task's would: a change that never waits (a lone session's act
            # on the server that holds it) completes without a task and the two turns of the loop it costs.
            try:
                waits_for = work.send(None)
            except StopIteration as done:
                return done.value
            task = asyncio.ensure_future(_Resumed(work, waits_for).run())
        else:
            task = asyncio.ensure_future(work)  # the task copies the context: it runs with `unit` current
    finally:
        _CURRENT.reset(token)
    try:
        return await asyncio.shield(task)
    except asyncio.CancelledError:
        if unit.cancellable:
            unit.dropped = True
            task.cancel()  # nothing applied yet: it never happened
        elif undo is not None:
            _orphan(asyncio.ensure_future(_undone(task, undo)))
        elif not task.done():
            _orphan(task)
        raise


class _Resumed:
    """A coroutine that `run_whole` started, driven on from where it first waits, as its own task would drive it."""

    __slots__ = ("coro", "waits_for")

    def __init__(self, coro: Coroutine, waits_for: object) -> None:
        self.coro, self.waits_for = coro, waits_for

    async def run(self):
        return await self

    def __await__(self):
        coro, waits_for = self.coro, self.waits_for
        while True:
            try:
                yield waits_for  # the task waits for what the coroutine waits for ...
            except BaseException as e:  # noqa: BLE001 - thrown in by the task (a cancellation): passed on
                try:
                    waits_for = coro.throw(e)
                except StopIteration as done:
                    return done.value
                continue
            return (yield from coro.__await__())  # ... then resumes it, and the task drives it from there


async def _undone(task: asyncio.Future[T], undo: Callable[[T], Awaitable[object]]) -> None:
    """Wait for `task` (a change whose caller went away), then undo what it made."""
    result = await task
    await undo(result)


def _orphan(task: asyncio.Future) -> None:
    _orphans.add(task)
    task.add_done_callback(_orphan_done)


def _orphan_done(task: asyncio.Task) -> None:
    _orphans.discard(task)
    if task.cancelled():
        return
    e = task.exception()  # retrieved, so asyncio does not warn; a service error was the caller's answer
    if e is not None and not hasattr(e, "grpc_code"):
        log.error("a change whose caller went away failed", exc_info=e)
