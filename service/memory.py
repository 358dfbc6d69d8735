"""The server process's heap: handing freed memory back to the OS soon after a burst of frees (glibc's
`malloc_trim`), keeping the objects of startup out of the garbage collector's passes, and running its youngest
pass less often."""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import gc

# Allocations (less frees) between two passes over the youngest objects (Python's default: 700). Under load every
# request in flight holds young objects (its coroutines, futures, scope); at 700 each pass walks them all again and
# moves them on to the next generation, whose passes walk them once more: the collector took ~12% of the event
# loop's time with 256 REST sessions acting. Most of that garbage is freed by reference counting; this only bounds
# how long cyclic garbage waits. 10,000: REST at 256 sessions +14% in memory, +15% over the replicated store (one
# run each here); 50,000 measured no better (docs/performance.md).
YOUNG_THRESHOLD = 10_000


def return_freed_memory() -> None:
    """`malloc_trim(0)`: glibc keeps the pages of freed memory in its arenas (one per thread that allocated it)
    until told to return them; a no-op without glibc."""
    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def freeze_startup_heap() -> int:
    """Collect once, then move every object alive now (torch, the models, the apps: ~250,000 objects) into the
    collector's permanent generation (`gc.freeze`), and collect the youngest objects every `YOUNG_THRESHOLD`
    allocations from then on; returns how many objects the permanent generation holds.

    Every full collection otherwise walks them all: ~80 ms each on the event loop, timed with `gc.callbacks`
    (POST /act with 256 sessions: p99 144 ms -> 33 ms, acts/s +14%, in one run here; docs/performance.md).
    Frozen objects are still freed when their last reference goes; only a reference cycle among them is kept.
    """
    gc.collect()
    gc.freeze()
    _, older, oldest = gc.get_threshold()
    gc.set_threshold(YOUNG_THRESHOLD, older, oldest)
    return gc.get_freeze_count()


class Trimmer:
    """Runs `return_freed_memory` in a worker thread `delay_s` after the first `soon()` since its last run, so
    that many streams closing together cost one trim (0.4-10 ms measured here, off the event loop).

    Args:
        delay_s: How long after the first request the trim runs.
    """

    def __init__(self, delay_s: float = 1.0) -> None:
        self.delay_s = delay_s
        self.runs = 0
        self._pending: asyncio.TimerHandle | None = None

    def soon(self) -> None:
        """Ask for a trim (from the event loop)."""
        if self._pending is None:
            loop = asyncio.get_running_loop()
            self._pending = loop.call_later(self.delay_s, self._run, loop)

    def _run(self, loop: asyncio.AbstractEventLoop) -> None:
        self._pending = None
        self.runs += 1
        loop.run_in_executor(None, return_freed_memory)

    def cancel(self) -> None:
        """Drop a pending trim (on shutdown)."""
        if self._pending is not None:
            self._pending.cancel()
            self._pending = None
