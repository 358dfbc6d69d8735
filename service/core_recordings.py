"""The core's recordings and timelines: which sessions record, their recordings written when they close or expire
(`gmt.common.recording`), read while they live, and the pages of their goal timeline.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from pathlib import Path

from gmt.common.recording import Recording
from gmt.service.core_state import CoreState
from gmt.service.errors import Aborted, FailedPrecondition, InvalidArgument, NotFound
from gmt.service.ids import check_session_id, short_id
from gmt.service.records import assemble, decode_timeline, record_drawn
from gmt.service.sessions import Session
from gmt.service.views import MAX_LIST_OFFSET, MAX_TIMELINE_PAGE, TimelineView

log = logging.getLogger("gmt.core")


class Recordings(CoreState):
    """Recordings and timelines, a part of `gmt.service.core.Core` (it owns `_archives`, the recordings being
    written)."""

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
