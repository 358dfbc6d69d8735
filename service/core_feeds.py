"""The core's feeds: what it tells watchers and metrics about sessions. Every event of the per-session feed
(`gmt.service.events`: `act`, `goal`, `reset`, `closed`, `expired`) and the session counts of the metrics
(`gmt.service.metrics`) are written here, so their shapes have one owner."""

from __future__ import annotations

import time

from gmt.service.core_state import CoreState
from gmt.service.records import Report
from gmt.service.sessions import Session
from gmt.service.views import ActResult, SessionView


class Feeds(CoreState):
    """Events and session metrics, a part of `gmt.service.core.Core`."""

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

    def _goal_set(self, view: SessionView, goal: int, given: dict, blend_steps: int) -> None:
        """Tell the session's watchers of a change to `goal` (`view.step`: the first act that uses it)."""
        if view.session_id in self.events:
            data = {"goal": goal, "goal_name": view.goal_name, "step": view.step, "given": given}
            self.events.publish(view.session_id, "goal", {**data, "blend_steps": blend_steps})

    def _was_reset(self, view: SessionView) -> None:
        """Tell the session's watchers of a new episode."""
        if view.session_id in self.events:
            self.events.publish(
                view.session_id, "reset", {"goal": view.goal, "goal_name": view.goal_name, "step": 0}
            )

    def _ended(self, sid: str, why: str) -> None:
        """End the session's feed: `closed` or `expired`."""
        self.events.end(sid, why, {"session_id": sid})

    async def _count_live(self) -> None:
        """Set the live-session gauge from the store."""
        self.metrics.live_sessions.set(await self.store.count())
