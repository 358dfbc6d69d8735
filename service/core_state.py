"""The state the core's parts share, made once: `Core` and each of its parts (`core_versions`, `core_sessions`,
`core_acts`, `core_recordings`) are a `CoreState`, so each part reads and writes these attributes and nothing else
of another part's."""

from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor

from gmt.service import keys
from gmt.service.batcher import MicroBatcher
from gmt.service.events import EventHub
from gmt.service.ids import SessionLocks
from gmt.service.metrics import Metrics
from gmt.service.model_state import ModelState, NoModelState
from gmt.service.registry import ModelRegistry
from gmt.service.sessions import Clock, SessionStore
from gmt.service.settings import Settings


class CoreState:
    """What every part of the core holds.

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
        self._lock = SessionLocks()  # one lock per session, taken by every part (`gmt.service.ids`)
        self._sweeper: asyncio.Task | None = None
        self.events = EventHub()  # per-session event feeds of this replica (`GET /sessions/{id}/events`)
        self._archives: set[asyncio.Task] = set()  # recordings being written (expired sessions)
        self.model_state: ModelState = NoModelState()  # where each model's default and canary are kept
