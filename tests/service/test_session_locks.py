"""The per-session locks' `busy`: what the idle sweep asks before it takes a session's lock (it must never wait)."""

from __future__ import annotations

import asyncio

from gmt.service.ids import SessionLocks


def _taken_at_once(lock: asyncio.Lock) -> bool:
    """Whether `lock.acquire()` completes without suspending (then the lock is held)."""
    coro = lock.acquire()
    try:
        coro.send(None)
    except StopIteration:
        return True
    coro.close()  # it would have waited
    return False


def test_busy_while_held_and_while_handed_to_a_waiter_that_has_not_run():
    """A released lock with a waiter is handed over before the waiter runs: `busy` says so (taking it would wait);
    a cancelled waiter does not count; a lock that is not busy is taken without waiting."""

    async def main():
        locks = SessionLocks()
        seen = [locks.busy("a")]
        lock = locks("a")
        await lock.acquire()
        seen.append(locks.busy("a"))
        waiter = asyncio.ensure_future(lock.acquire())
        await asyncio.sleep(0)  # one turn: the waiter runs up to its wait on the lock
        lock.release()  # handed to the waiter, which has not run yet
        seen.append((lock.locked(), locks.busy("a")))
        await waiter
        lock.release()
        await lock.acquire()
        gone = asyncio.ensure_future(lock.acquire())
        await asyncio.sleep(0)
        gone.cancel()
        lock.release()
        seen.append(locks.busy("a"))  # its only waiter was cancelled
        seen.append(_taken_at_once(lock))
        return seen

    assert asyncio.run(main()) == [False, True, (False, True), False, True]
