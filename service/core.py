"""The transport-agnostic service: models and their versions, sessions, goals and batched actions. The adapters
(REST, gRPC, the console) call this.

`Core` is assembled from its parts, one job each: `core_versions` (the model-version control plane),
`core_sessions` (session calls), `core_acts` (the act path), `core_recordings` (recordings and timelines) and
`core_feeds` (events and session metrics). They share the state `core_state.CoreState` makes: the settings,
registry, store, clock, metrics, event feed and the per-session lock (`gmt.service.ids`). Ids are checked by
`gmt.service.ids`; answers are `gmt.service.views`.
"""

from __future__ import annotations

import asyncio
import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from gmt.service.core_acts import Acts
from gmt.service.core_feeds import Feeds
from gmt.service.core_recordings import Recordings
from gmt.service.core_sessions import Sessions
from gmt.service.core_versions import Versions
from gmt.service.errors import ServiceError, Unavailable
from gmt.service.ids import short_id
from gmt.service.registry import ModelRegistry
from gmt.service.sessions import MemorySessionStore

log = logging.getLogger("gmt.core")


class Core(Versions, Sessions, Acts, Recordings, Feeds):
    """Loads models, keeps sessions and answers requests; knows nothing of HTTP or gRPC.

    Args:
        settings: Server settings.
        registry: Models to serve (default: loaded from `settings.checkpoints` by `start`).
        store: Session store (default: Redis if `settings.redis_url`, else memory).
        clock: Wall-clock seconds used for idle timeouts (injectable for tests).
    """

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
        self.store.locks = self._lock
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
        # Each expired session's engine slot was freed by the store (`on_remove`) while its lock was free.
        gone = await self.store.sweep()
        for s in gone:
            self._ended(s.id, "expired")
            log.info("session expired", extra={"session": short_id(s.id), "model": s.key})
        for m in self.registry.loaded():  # a shared store lets go of sessions it stopped seeing
            self._unload_if_drained(m)
        self.metrics.sessions_expired.inc(len(gone))
        await self._count_live()
        return len(gone)

    def _check_serving(self) -> None:
        if self.closing or not self.started:
            raise Unavailable("server is shutting down" if self.closing else "server is starting")
