"""A failover drill: sessions act through a running cluster (`gmt cluster up`) while its Redis primary is killed
with SIGKILL; it records how long acts stopped, every answer that was not a success (by kind), and each
episode's actions, to compare with an uninterrupted twin's (`twin_actions`).

Each session acts as a careful client does: every act names its step, and an answer that applied nothing or may
have been applied (REST 502 / 503 / 409 `aborted`, gRPC UNAVAILABLE / ABORTED / a reset stream, a broken
connection) is sent again, with the same step, every `retry_s`, for at most `act_deadline_s`; any other answer
ends the episode. Sessions take turns in the three ways to act through nginx: REST `POST /sessions/{id}/act`,
gRPC unary `Act`, and a gRPC `Control` stream.

`bench_failover` is `gmt bench --sections failover`: the drill on a fresh `gmt cluster`, summarised.
"""

from __future__ import annotations

import asyncio
import os
import re
import shutil
import signal
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gmt.cluster.supervisor import Cluster

KINDS = ("rest", "grpc", "stream")


class _Retry(Exception):
    """An answer worth sending again (with the same step).

    Args:
        kind: What it was, e.g. "rest 503 unavailable".
        message: The error message it carried ("" if none).
    """

    def __init__(self, kind: str, message: str = "") -> None:
        super().__init__(kind)
        self.kind, self.message = kind, message


class _Final(Exception):
    """An answer that ends the episode."""


@dataclass
class Episode:
    """One session of the drill.

    Attributes:
        kind: How it acts: rest, grpc (unary Act) or stream (Control).
        session_id: Its id.
        goal: The goal it was created with.
        seed: The seed it was created with (sampled actions depend on it).
        observations: One row per step it may take.
        actions: The action answered for each step taken, in order.
        sent: When each step's act was first sent (time.monotonic()).
        answered: When each step's answer came.
        failure: What ended it early (an answer that is not retried, or retries past the deadline).
    """

    kind: str
    session_id: str
    goal: int
    seed: int
    observations: np.ndarray
    actions: list[np.ndarray] = field(default_factory=list)
    sent: list[float] = field(default_factory=list)
    answered: list[float] = field(default_factory=list)
    failure: str | None = None

    def answered_after(self, t: float) -> int:
        """Steps whose act was first sent after `t` and is answered."""
        return sum(1 for s in self.sent if s > t)


@dataclass
class Drill:
    """What a drill saw.

    Attributes:
        killed: The Redis server killed (the primary when the drill began).
        promoted: The Redis server the sentinels named as the primary afterwards.
        killed_at: When it was killed (time.monotonic()).
        episodes: Every session's episode.
        errors: Answers that were sent again, by kind (e.g. "rest 503 unavailable", "grpc UNAVAILABLE").
        examples: The distinct messages of each kind in `errors` (digits as N; the first 5 kinds of message).
        lost: Sessions that are gone, or whose stored step is not the number of steps answered.
    """

    killed: str
    promoted: str | None
    killed_at: float
    episodes: list[Episode]
    errors: dict[str, int]
    examples: dict[str, list[str]]
    lost: list[str]

    @property
    def resume_s(self) -> float:
        """Seconds from the kill until every session had an answer to an act it sent after the kill."""
        firsts = [next((a for s, a in zip(e.sent, e.answered, strict=True) if s > self.killed_at), None)
                  for e in self.episodes]  # fmt: skip
        if any(f is None for f in firsts):
            return float("inf")
        return max(firsts) - self.killed_at

    @property
    def first_answer_s(self) -> float:
        """Seconds from the kill until the first answer to an act sent after it (any session)."""
        after = [
            a for e in self.episodes for s, a in zip(e.sent, e.answered, strict=True) if s > self.killed_at
        ]
        return min(after) - self.killed_at if after else float("inf")

    def summary(self, twins: list[list[np.ndarray]] | None = None) -> dict:
        """Plain figures (JSON); with `twins`, how many sessions' actions differ from their twin's."""
        steps = [len(e.actions) for e in self.episodes]
        out = {
            "sessions": len(self.episodes),
            "by_kind": dict(Counter(e.kind for e in self.episodes)),
            "killed": self.killed,
            "promoted": self.promoted,
            "resume_s": round(self.resume_s, 3),
            "first_answer_after_kill_s": round(self.first_answer_s, 3),
            "steps_answered": sum(steps),
            "steps_per_session": [min(steps), max(steps)],
            "retried_answers": dict(sorted(self.errors.items())),
            "messages_by_kind": dict(sorted(self.examples.items())),
            "failed_sessions": {e.session_id: e.failure for e in self.episodes if e.failure},
            "lost_sessions": self.lost,
        }
        if twins is not None:
            out["sessions_unlike_twin"] = sum(
                1 for e, w in zip(self.episodes, twins, strict=True) if not _same(e.actions, w)
            )
        return out


def _same(got: list[np.ndarray], want: list[np.ndarray]) -> bool:
    return len(got) == len(want) and all(np.array_equal(g, w) for g, w in zip(got, want, strict=True))


def twin_actions(checkpoint: Path, episodes: list[Episode]) -> list[list[np.ndarray]]:
    """Each episode's actions as an uninterrupted session (same goal, seed and observations) takes them, computed
    by an engine of its own over `checkpoint`."""
    from gmt.model.checkpoint import load_checkpoint
    from gmt.model.engine import PolicyEngine

    engine = PolicyEngine(load_checkpoint(checkpoint))
    out = []
    for i, e in enumerate(episodes):
        ctx = engine.new_context(e.goal, seed=e.seed, key=f"twin-{i}")
        out.append([np.asarray(engine.act([ctx], [o])[0]) for o in e.observations[: len(e.actions)]])
        engine.forget(f"twin-{i}")
    return out


def _error(r) -> tuple[str, str]:
    """(code, message) of an error answer in the service's envelope; ("", its first bytes) otherwise."""
    try:
        err = r.json().get("error")
    except (ValueError, AttributeError):
        err = None
    if isinstance(err, dict):
        return str(err.get("code", "")), str(err.get("message", ""))
    return "", r.text[:200]


class _Actor:
    """Sends one act of an episode by its kind and sorts the answer: an action, `_Retry` or `_Final`."""

    def __init__(self, http, stub) -> None:
        self.http, self.stub = http, stub
        self.streams: dict[str, object] = {}  # session id -> open Control call

    async def act(self, e: Episode, t: int) -> np.ndarray:
        import grpc

        try:
            if e.kind == "rest":
                return await self._rest(e, t)
            if e.kind == "grpc":
                from gmt.client.grpc import act_from_proto, act_request

                r = await self.stub.Act(
                    act_request(e.session_id, e.observations[t], t),
                    metadata=(("x-session-id", e.session_id),),
                    timeout=10,
                )
                return self._checked(e, t, act_from_proto(r))
            return await self._stream(e, t)
        except grpc.RpcError as err:
            self.close(e.session_id)
            code = err.code()
            kind = f"{e.kind} {code.name}"
            if code in (
                grpc.StatusCode.UNAVAILABLE,
                grpc.StatusCode.ABORTED,
                grpc.StatusCode.DEADLINE_EXCEEDED,
            ):
                raise _Retry(kind, err.details() or "") from None
            if code == grpc.StatusCode.INTERNAL and "RST_STREAM" in (err.details() or ""):
                raise _Retry(f"{kind} RST_STREAM", err.details() or "") from None
            raise _Final(f"{kind}: {err.details()}") from None

    async def _rest(self, e: Episode, t: int) -> np.ndarray:
        import httpx

        body = {"observation": e.observations[t].tolist(), "step": t}
        try:
            r = await self.http.post(f"/sessions/{e.session_id}/act", json=body)
        except httpx.TransportError as err:
            raise _Retry(f"rest {type(err).__name__}") from None
        if r.status_code == 200:
            d = r.json()
            if d["step"] != t:
                raise _Final(f"rest answered step {d['step']} for step {t}")
            return np.asarray(d["action"], dtype=np.float32)
        code, message = _error(r)
        kind = f"rest {r.status_code} {code}".rstrip()
        if r.status_code in (502, 503) or (r.status_code == 409 and code == "aborted"):
            raise _Retry(kind, message)
        raise _Final(f"{kind}: {r.text[:300]}")

    async def _stream(self, e: Episode, t: int) -> np.ndarray:
        import grpc

        from gmt.client.grpc import act_from_proto, act_request
        from gmt.v1 import policy_pb2 as pb

        call = self.streams.get(e.session_id)
        if call is None:
            call = self.streams[e.session_id] = self.stub.Control(metadata=(("x-session-id", e.session_id),))
        try:
            await call.write(pb.ControlRequest(act=act_request(e.session_id, e.observations[t], t)))
            r = await asyncio.wait_for(call.read(), 10)
        except TimeoutError:
            self.close(e.session_id)
            raise _Retry("stream no answer in 10 s") from None
        except asyncio.InvalidStateError:  # the call had already ended (its status is read on the next try)
            self.close(e.session_id)
            raise _Retry("stream ended") from None
        if r is grpc.aio.EOF:
            self.close(e.session_id)
            raise _Retry("stream closed")
        if r.WhichOneof("result") == "error":
            kind = f"stream {r.error.code} (in-band)"
            if r.error.code in ("unavailable", "aborted"):
                self.close(
                    e.session_id
                )  # as the Python client does: a new stream may reach a replica that serves
                raise _Retry(kind, r.error.message)
            raise _Final(f"{kind}: {r.error.message}")
        return self._checked(e, t, act_from_proto(r.act))

    @staticmethod
    def _checked(e: Episode, t: int, result) -> np.ndarray:
        if result.step != t:
            raise _Final(f"{e.kind} answered step {result.step} for step {t}")
        return np.asarray(result.action)

    def close(self, sid: str) -> None:
        call = self.streams.pop(sid, None)
        if call is not None:
            call.cancel()


async def _episode(e: Episode, actor: _Actor, stop: asyncio.Event, seen: tuple[Counter, dict], cfg: dict):
    for t in range(len(e.observations)):
        if stop.is_set():
            break
        sent = time.monotonic()
        while True:
            try:
                action = await actor.act(e, t)
                break
            except _Retry as r:
                seen[0][r.kind] += 1
                shapes = seen[1].setdefault(r.kind, [])
                shape = re.sub(r"\d+", "N", r.message)
                if shape not in shapes and len(shapes) < 5:
                    shapes.append(shape)
                if time.monotonic() - sent > cfg["act_deadline_s"]:
                    e.failure = f"step {t}: retried for {cfg['act_deadline_s']} s, last {r.kind}: {r.message}"
                    return
                await asyncio.sleep(cfg["retry_s"])
            except _Final as f:
                e.failure = f"step {t}: {f}"
                return
        e.actions.append(action)
        e.sent.append(sent)
        e.answered.append(time.monotonic())
        if cfg["pace_s"]:
            await asyncio.sleep(cfg["pace_s"])
    actor.close(e.session_id)


async def _until(ready: Callable[[], bool], tasks: list[asyncio.Task], timeout_s: float) -> bool:
    """Poll `ready` until true (True), every task ended or `timeout_s` passed (False)."""
    deadline = time.monotonic() + timeout_s
    while not ready():
        if all(t.done() for t in tasks) or time.monotonic() > deadline:
            return False
        await asyncio.sleep(0.02)
    return True


def run_drill(
    c: Cluster,
    model: str,
    *,
    sessions: int,
    obs_dim: int,
    goals: int = 1,
    steps_before: int = 5,
    steps_after: int = 5,
    max_steps: int = 1000,
    pace_s: float = 0.0,
    retry_s: float = 0.05,
    act_deadline_s: float = 30.0,
    phase_timeout_s: float = 60.0,
    seed: int = 0,
) -> Drill:
    """Create `sessions` sessions, let each take `steps_before` steps, SIGKILL the Redis primary, and stop once
    each has taken `steps_after` more steps sent after the kill.

    Args:
        c: A running cluster (its Redis primary is killed and not restarted).
        model: The model every session runs (continuous actions).
        sessions: Sessions, taking turns in the kinds of `KINDS`.
        obs_dim: The model's observation size.
        goals: Sessions take turns in goals 0..goals-1.
        steps_before: Steps every session takes before the kill.
        steps_after: Steps every session takes, sent after the kill, before the drill ends.
        max_steps: Most steps a session takes (its observations are drawn up front).
        pace_s: Pause after each answer (0: act again at once).
        retry_s: Pause before sending an act again.
        act_deadline_s: Longest a session retries one act before it gives up (a failure).
        phase_timeout_s: Longest wait for each phase (steps before, steps after).
        seed: Seeds the observations and the sessions' seeds.

    Raises:
        RuntimeError: a phase did not complete (the episodes' failures say why).
    """
    import grpc
    import httpx

    from gmt.v1 import policy_pb2_grpc

    rng = np.random.default_rng(seed)
    killed = c.primary()
    if killed is None:
        raise RuntimeError("the sentinels name no primary")
    cfg = {"pace_s": pace_s, "retry_s": retry_s, "act_deadline_s": act_deadline_s}

    async def main() -> Drill:
        limits = httpx.Limits(max_connections=sessions + 8, max_keepalive_connections=sessions + 8)
        async with (
            httpx.AsyncClient(base_url=c.rest_url, timeout=10, limits=limits) as http,
            grpc.aio.insecure_channel(c.grpc_target) as channel,
        ):
            episodes = []
            for i in range(sessions):
                goal, s = i % goals, int(rng.integers(2**62))
                r = await http.post("/sessions", json={"model": model, "goal": goal, "seed": s})
                r.raise_for_status()
                obs = rng.normal(size=(max_steps, obs_dim)).astype(np.float32)
                episodes.append(Episode(KINDS[i % len(KINDS)], r.json()["session_id"], goal, s, obs))
            actor = _Actor(http, policy_pb2_grpc.PolicyServiceStub(channel))
            stop, errors, examples = asyncio.Event(), Counter(), {}
            tasks = [asyncio.create_task(_episode(e, actor, stop, (errors, examples), cfg)) for e in episodes]
            try:
                if not await _until(lambda: all(len(e.actions) >= steps_before for e in episodes), tasks,
                                    phase_timeout_s):  # fmt: skip
                    raise RuntimeError(
                        f"the sessions did not take {steps_before} steps: {_failures(episodes)}"
                    )
                killed_at = time.monotonic()
                os.kill(c.pids[killed], signal.SIGKILL)
                if not await _until(lambda: all(e.answered_after(killed_at) >= steps_after for e in episodes),
                                    tasks, phase_timeout_s):  # fmt: skip
                    raise RuntimeError(
                        f"the sessions did not take {steps_after} steps after the kill: {_failures(episodes)}"
                    )
            finally:
                stop.set()
                await asyncio.gather(*tasks)
            promoted = await asyncio.to_thread(c.primary)
            lost = []
            for e in episodes:
                r = await http.get(f"/sessions/{e.session_id}")
                if r.status_code != 200 or r.json()["step"] != len(e.actions):
                    lost.append(e.session_id)
                await http.delete(f"/sessions/{e.session_id}")
            return Drill(killed, promoted, killed_at, episodes, dict(errors), examples, lost)

    return asyncio.run(main())


def _failures(episodes: list[Episode]) -> dict[str, str]:
    return {e.session_id: e.failure for e in episodes if e.failure} or {"none": "still running"}


def bench_failover(checkpoint: Path, sessions: int = 64, steps: int = 20) -> dict:
    """The Redis primary of a `gmt cluster` killed (SIGKILL) while `sessions` sessions act as fast as they can
    (REST, gRPC unary and Control streams in turn): time to resume, retried answers by kind, sessions lost, and
    sessions whose actions differ from an uninterrupted twin's (the drill above)."""
    import httpx

    from gmt.cluster import supervisor as cluster

    run_dir = Path(tempfile.mkdtemp(prefix="gmt-failover-"))
    c = cluster.up(
        run_dir, rest_port=0, grpc_port=0, checkpoints=[checkpoint], serve_args=["--max-sessions", "4096"]
    )
    try:
        name = httpx.get(f"{c.rest_url}/models", timeout=30).json()["models"][0]["name"]
        spec = httpx.get(f"{c.rest_url}/models/{name}", timeout=30).json()
        d = run_drill(
            c,
            name,
            sessions=sessions,
            obs_dim=int(np.prod(spec["observation_space"]["shape"])),
            goals=len(spec["goals"]),
            steps_before=steps,
            steps_after=steps,
        )
    finally:
        cluster.down(run_dir, quiet=True)
        shutil.rmtree(run_dir, ignore_errors=True)
    before = [a for e in d.episodes for a in e.answered if a <= d.killed_at]
    first = min(s for e in d.episodes for s in e.sent)
    out = d.summary(twin_actions(checkpoint, d.episodes))
    out["acts_per_s_before_kill"] = round(len(before) / (d.killed_at - first), 1)
    return out
