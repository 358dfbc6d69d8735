"""MicroBatcher alone, with a recording engine: batch bounds, waiting only for acting sessions, cancellation,
failures. Contexts are plain names here (a session is its context's `slot`, or the context itself)."""

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor

import pytest
from service_harness import FakeClock

from gmt.service.batcher import INLINE_ROWS, REMOTE_STORE_PARTS, SPLIT_FROM, MicroBatcher


class RecordingEngine:
    """Answers each observation with itself; records batch sizes; can be held at a gate or made to fail."""

    def __init__(self) -> None:
        self.batches: list[list] = []
        self.gate = threading.Event()
        self.gate.set()
        self.entered = threading.Event()
        self.fail = False
        self.threads: list[str] = []
        self.split: list[int] = []  # the `threads` each pass was given

    def act(self, contexts, observations, prepared=False, threads=1):
        self.threads.append(threading.current_thread().name)
        self.split.append(threads)
        self.entered.set()
        self.gate.wait(30)
        self.batches.append(list(observations))
        if self.fail:
            raise RuntimeError("boom")
        return list(observations)


def run(coro):
    return asyncio.run(coro)


async def held_pass(eng: RecordingEngine, executor, value, **kw) -> tuple[MicroBatcher, asyncio.Future]:
    """A started batcher (no batch wait) whose first pass, acting `value`, is held at the engine's gate (closed
    here): the batcher and that pass's caller."""
    eng.gate.clear()
    b = MicroBatcher(eng, executor, max_batch=64, max_wait_s=0, **kw)
    b.start()
    first = asyncio.ensure_future(b.act(None, value))
    assert await asyncio.to_thread(eng.entered.wait, 5)
    return b, first


@pytest.fixture
def pool():
    with ThreadPoolExecutor(1) as p:
        yield p


def test_batches_never_exceed_max_batch(pool):
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=2, max_wait_s=0.05)
        b.start()
        out = await asyncio.gather(*(b.act(None, i) for i in range(5)))
        await b.close()
        return out

    assert run(main()) == [0, 1, 2, 3, 4]
    assert [len(x) for x in eng.batches] == [2, 2, 1]


async def in_step(b: MicroBatcher, names: list[str], rounds: int = 1) -> None:
    """Every named session acts at once, `rounds` times."""
    for r in range(rounds):
        await asyncio.gather(*(b.act(n, f"{n}{r}") for n in names))


def test_waits_for_an_acting_session_then_runs(pool):
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=10)
        b.start()
        await in_step(b, ["a", "b", "c"])
        assert b.waits == 0  # all three arrived together: nobody acting was missing
        first = [asyncio.ensure_future(b.act(n, f"{n}!")) for n in ("a", "b")]
        while b.waits < 1:  # the batch of a and b waits for c, which is acting
            await asyncio.sleep(0)
        out = await asyncio.wait_for(asyncio.gather(*first, b.act("c", "c!")), 5)  # far less than max_wait_s
        await b.close()
        return out

    assert run(main()) == ["a!", "b!", "c!"]
    assert eng.batches[-1] == ["a!", "b!", "c!"]


def test_sessions_that_stopped_acting_are_not_waited_for(pool):
    """A session answered longer ago than the acting window no longer holds a batch; one that never acted (an
    idle session) never did."""
    eng = RecordingEngine()
    clock = FakeClock()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=0.01, clock=clock)
        b.start()
        await in_step(b, ["busy", "stopped"])
        clock.advance(b.active_window_s / 2)
        assert await asyncio.wait_for(b.act("busy", "held"), 5) == "held"
        assert b.waits == 1  # "stopped" still counted as acting: the batch waited for it (10 ms)
        clock.advance(b.active_window_s)
        for i in range(5):
            assert await asyncio.wait_for(b.act("busy", i), 5) == i
        await b.close()
        return b.waits

    assert run(main()) == 1
    assert eng.batches[-5:] == [[i] for i in range(5)]


def test_wait_is_bounded(pool):
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=0.01)
        b.start()
        await in_step(b, ["a", "late"])
        out = await asyncio.wait_for(b.act("a", 1), 5)  # "late" is acting and does not come
        await b.close()
        return out, b.waits

    assert run(main()) == (1, 1) and eng.batches[-1] == [1]


def test_cancelled_request_is_dropped_before_the_forward(pool):
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=10)
        b.start()
        await in_step(b, ["doomed", "kept", "last"])
        doomed = asyncio.ensure_future(b.act("doomed", "doomed"))
        kept = asyncio.ensure_future(b.act("kept", "kept"))
        while b.waits < 1:  # both queued; the batcher waits for "last", acting
            await asyncio.sleep(0)
        doomed.cancel()
        out = await asyncio.wait_for(asyncio.gather(kept, b.act("last", "last")), 5)
        await b.close()
        return out

    assert run(main()) == ["kept", "last"]
    assert eng.batches[-1] == ["kept", "last"]


def three_rounds(eng: RecordingEngine, executor, names: list[str], max_wait_s: float, parts: int = 2) -> None:
    """Every named session acts at once, three rounds, through a batcher with room for all of them."""

    async def main():
        b = MicroBatcher(eng, executor, max_batch=1024, max_wait_s=max_wait_s, parts=parts)
        b.start()
        await asyncio.wait_for(in_step(b, names, rounds=3), 10)
        await b.close()

    run(main())


@pytest.mark.parametrize("parts", [2, REMOTE_STORE_PARTS])
@pytest.mark.parametrize("acting", [SPLIT_FROM - 1, SPLIT_FROM, 2 * SPLIT_FROM + 1, 4 * SPLIT_FROM + 1])
def test_many_acting_sessions_are_taken_a_part_per_pass(pool, acting, parts):
    """From `SPLIT_FROM` sessions acting one at a time, a pass takes at most their share even below `max_batch`
    (the loop answers one part while the engine runs another): half, or with a remote store a quarter but no fewer
    than `SPLIT_FROM` nor more than half; fewer acting sessions go in one pass. No wait here: a round's sessions are
    all queued before its first pass."""
    eng = RecordingEngine()
    three_rounds(eng, pool, [f"s{i}" for i in range(acting)], max_wait_s=0, parts=parts)
    assert len(eng.batches[0]) == acting  # nobody had acted yet: one pass
    later = [len(x) for x in eng.batches[1:]]
    half = -(-acting // 2)
    want = {  # (acting, parts) -> the most a pass takes
        (SPLIT_FROM - 1, 2): acting,
        (SPLIT_FROM - 1, 4): acting,
        (SPLIT_FROM, 2): half,
        (SPLIT_FROM, 4): half,  # a quarter would be under SPLIT_FROM: half, the most it may take
        (2 * SPLIT_FROM + 1, 2): half,
        (2 * SPLIT_FROM + 1, 4): SPLIT_FROM,  # a quarter would be under SPLIT_FROM
        (4 * SPLIT_FROM + 1, 2): half,
        (4 * SPLIT_FROM + 1, 4): SPLIT_FROM + 1,  # a quarter, rounded up
    }[(acting, parts)]
    assert sum(later) == 2 * acting and max(later) == want, later


def test_without_an_executor_passes_are_not_split():
    """The naive server's forward runs on the loop, which nothing would overlap: whole passes."""
    eng = RecordingEngine()
    three_rounds(eng, None, [f"s{i}" for i in range(2 * SPLIT_FROM)], max_wait_s=10)
    assert [len(x) for x in eng.batches] == [2 * SPLIT_FROM] * 3


def test_requests_arriving_during_a_forward_form_the_next_batch(pool):
    eng = RecordingEngine()

    async def main():
        b, first = await held_pass(eng, pool, 0)  # the forward of [0] is running, held at the gate
        more = [asyncio.ensure_future(b.act(None, i)) for i in (1, 2, 3)]
        while b._live() < 3:
            await asyncio.sleep(0)
        eng.gate.set()
        out = await asyncio.wait_for(asyncio.gather(first, *more), 5)
        await b.close()
        return out

    assert run(main()) == [0, 1, 2, 3]
    assert eng.batches == [[0], [1, 2, 3]]


def test_a_failing_forward_fails_its_batch_only(pool):
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=0)
        b.start()
        eng.fail = True
        with pytest.raises(RuntimeError, match="boom"):
            await b.act(None, 1)
        eng.fail = False
        out = await b.act(None, 2)
        await b.close()
        return out

    assert run(main()) == 2


def test_a_crashed_batcher_fails_its_calls_as_unavailable_and_restarts(pool):
    from gmt.service.errors import Unavailable

    engine = RecordingEngine()

    async def main():
        b = MicroBatcher(engine, pool, max_batch=4, max_wait_s=0.0)
        b.start()
        real_gather = b._gather
        crashes = [RuntimeError("bug in the batching loop")]

        async def gather_once_broken(cap):
            if crashes:
                raise crashes.pop()
            await real_gather(cap)

        b._gather = gather_once_broken
        with pytest.raises(Unavailable, match="the batcher failed \\(RuntimeError\\); retry"):
            await b.act(None, 1)
        assert b.healthy and b.restarts == 1
        assert await b.act(None, 2) == 2  # the restarted loop serves the next call
        await b.close()
        assert not b.healthy

    run(main())


@pytest.mark.parametrize("inline_alone", [False, True])
def test_a_lone_session_runs_on_the_loop_only_when_asked_and_alone(pool, inline_alone):
    """With `inline_alone`, a batch of one with no other session acting runs on the event loop's thread (no hop);
    two sessions acting together are batched in the executor once both are acting; without the option, every
    forward runs in the executor."""
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=8, max_wait_s=0.5, inline_alone=inline_alone)
        b.start()
        assert await b.act("s", "alone") == "alone"
        await in_step(b, ["x", "y"], rounds=2)
        await b.close()
        return threading.current_thread().name

    loop_thread = run(main())
    assert eng.threads[0] == loop_thread if inline_alone else eng.threads[0] != loop_thread
    assert eng.threads[-1] != loop_thread
    assert eng.batches[0] == ["alone"] and eng.batches[-1] == ["x1", "y1"]


def test_a_small_call_runs_on_the_loop_only_while_nothing_else_is_batched(pool):
    """With `inline_alone`, a call of at most INLINE_ROWS rows on an idle batcher runs on the event loop's thread;
    a larger call and a call while sessions act one at a time go through the executor; a failing pass run on the
    loop answers as a batched one does (per row, the failure as its result)."""
    eng = RecordingEngine()
    clock = FakeClock()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=0.5, inline_alone=True, clock=clock)
        b.start()
        small = await b.act_many([f"s{i}" for i in range(INLINE_ROWS)], [f"s{i}" for i in range(INLINE_ROWS)])
        big = await b.act_many(
            [f"b{i}" for i in range(INLINE_ROWS + 1)], [f"b{i}" for i in range(INLINE_ROWS + 1)]
        )
        await in_step(b, ["x", "y"])  # x and y act one at a time now
        beside = await b.act_many(["c"], ["c0"])
        clock.advance(b.active_window_s + 1)  # x and y stop counting as acting
        eng.fail = True
        failed = await b.act_many(["d"], ["d0"])
        await b.close()
        return threading.current_thread().name, small, big, beside, failed

    loop_thread, small, big, beside, failed = run(main())
    assert small == [f"s{i}" for i in range(INLINE_ROWS)] and len(big) == INLINE_ROWS + 1 and beside == ["c0"]
    on_loop = {b[0]: t == loop_thread for b, t in zip(eng.batches, eng.threads, strict=True)}
    assert (on_loop["s0"], on_loop["b0"], on_loop["c0"], on_loop["d0"]) == (True, False, False, True)
    assert len(failed) == 1 and isinstance(failed[0], RuntimeError)


def test_a_served_session_beside_idle_sessions_of_its_model_never_waits(make_server, observations):
    """A real server with a minute-long batch wait: one session acts while five others of its model stay idle;
    every act is answered without waiting for them (before, each act waited the whole batch wait)."""
    import httpx

    srv = make_server(batch_wait_ms=60_000)
    with httpx.Client(base_url=srv.url, timeout=10) as http:  # an act held by the wait would time out
        sids = [
            http.post("/sessions", json={"model": "tiny-gmt", "goal": 1, "seed": i}).json()["session_id"]
            for i in range(6)
        ]
        for t, obs in enumerate(observations[:6]):
            r = http.post(f"/sessions/{sids[0]}/act", json={"observation": obs.tolist(), "step": t})
            assert r.status_code == 200, r.text
    assert [b.waits for b in srv.core._batchers.values()] == [0] * len(srv.core._batchers)


def test_a_solo_group_runs_in_a_pass_of_its_own_without_waiting_for_acting_sessions(pool):
    """Two solo groups queued together go in two passes (plain groups queued together share one), and a solo
    group first in line does not wait for the acting sessions, which could not join its pass anyway."""
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=10, call_threads=3)
        b.start()
        plain = await asyncio.wait_for(
            asyncio.gather(b.act_many(["e"], ["e0"]), b.act_many(["f"], ["f0"])), 5
        )
        await in_step(b, ["x", "y"])  # x and y are acting sessions now
        parts = await asyncio.wait_for(
            asyncio.gather(
                b.act_many(["a", "b"], ["a0", "b0"], solo=True),
                b.act_many(["c", "d"], ["c0", "d0"], solo=True),
            ),
            5,  # far less than max_wait_s
        )
        await b.close()
        return parts, plain, b.waits

    assert run(main()) == ([["a0", "b0"], ["c0", "d0"]], [["e0"], ["f0"]], 0)
    assert eng.batches == [["e0", "f0"], ["x0", "y0"], ["a0", "b0"], ["c0", "d0"]]
    assert eng.split == [3, 1, 3, 3]  # a call's pass may use call_threads; single acts' passes one


def test_closing_finishes_the_running_pass_and_fails_the_queued_requests_as_unavailable(pool):
    """A batcher closed while a pass runs in its thread answers that pass's callers (past their point of no return)
    before it stops; requests queued behind it never run and fail as unavailable (a retry is safe)."""
    from gmt.service.errors import Unavailable

    eng = RecordingEngine()

    async def main():
        b, running = await held_pass(eng, pool, 0)  # its pass is held at the gate
        queued = asyncio.ensure_future(b.act(None, 1))
        while b._live() < 1:
            await asyncio.sleep(0)
        closing = asyncio.ensure_future(b.close())
        while not b._task.cancelling():  # close() has cancelled the batching task; the pass is still held
            await asyncio.sleep(0)
        eng.gate.set()
        await asyncio.wait_for(closing, 5)
        first = await asyncio.wait_for(running, 5)
        with pytest.raises(Unavailable, match="before the request ran"):
            await asyncio.wait_for(queued, 5)
        return first

    assert run(main()) == 0
    assert eng.batches == [[0]]


def test_nothing_queued_for_a_dropped_change_starts(pool):
    """A call whose caller gave up before its point of no return (`units.Unit.dropped`) has nothing started by the
    batcher, even while the cancellation has not yet reached the requests it queued (a two-part call's second
    part)."""
    from gmt.service import units

    eng = RecordingEngine()

    async def main():
        b, first = await held_pass(eng, pool, 0)  # a pass held at the gate: the call queues behind it
        unit = units.Unit()
        token = units._CURRENT.set(unit)
        call = asyncio.ensure_future(b.act_many([None, None], [1, 2], solo=True))  # runs with `unit` current
        units._CURRENT.reset(token)
        while b._live() < 2:
            await asyncio.sleep(0)
        unit.dropped = True  # as run_whole marks it before cancelling the call
        eng.gate.set()
        assert await asyncio.wait_for(first, 5) == 0
        got = await asyncio.wait_for(call, 5)  # its requests cancelled, not run
        await b.close()
        return got

    assert [type(x) for x in run(main())] == [asyncio.CancelledError] * 2
    assert eng.batches == [[0]]


def test_a_crash_after_the_pass_fails_that_batchs_calls_as_unavailable(pool):
    """Should the loop fail after a pass ran but before it was answered (here its `observe` hook), the batch's
    callers are failed as unavailable by the supervisor, not left waiting; the restarted loop serves on."""
    from gmt.service.errors import Unavailable

    broken = [RuntimeError("bug in the metrics hook")]

    def observe(n, seconds):
        if broken:
            raise broken.pop()

    async def main():
        b = MicroBatcher(RecordingEngine(), pool, max_batch=4, max_wait_s=0.0, observe=observe)
        b.start()
        with pytest.raises(Unavailable, match="the batcher failed \\(RuntimeError\\); retry"):
            await asyncio.wait_for(b.act(None, 1), 5)
        answer = await b.act(None, 2)
        await b.close()
        return answer, b.restarts

    assert run(main()) == (2, 1)


def test_a_closing_batcher_cancelled_again_still_answers_its_running_pass(pool):
    """However often the batching task is cancelled while the pass it is finishing runs (close() called again, or
    its own caller cancelled), that pass's caller is answered and the task ends."""
    eng = RecordingEngine()

    async def main():
        b, running = await held_pass(eng, pool, 7)
        loop_coro = b._task.get_coro().cr_await  # the batching loop, which the supervising task awaits
        held = loop_coro.cr_await  # what it waits on: the running pass
        closing = asyncio.ensure_future(b.close())
        while loop_coro.cr_await is held:  # until the first cancellation is delivered and it waits again
            await asyncio.sleep(0)
        closing.cancel()  # close()'s caller gives up: the task is not cancelled through it
        again = loop_coro.cr_await
        b._task.cancel()  # and a second close() cancels the task once more
        while loop_coro.cr_await is again:
            await asyncio.sleep(0)
        eng.gate.set()
        answer = await asyncio.wait_for(running, 5)
        await asyncio.wait_for(b.close(), 5)
        return answer, b._task.done()

    assert run(main()) == (7, True)


def test_a_crash_while_answering_the_last_pass_does_not_hang_close(pool):
    """A batcher whose loop fails while it answers the pass it finished on closing fails that pass's callers as
    unavailable and stops (no restart that would wait for requests forever): close() returns."""
    from gmt.service.errors import Unavailable

    eng = RecordingEngine()
    state = {"closing": False}

    def observe(n, seconds):
        if state["closing"]:
            raise RuntimeError("bug in the metrics hook")

    async def main():
        b, running = await held_pass(eng, pool, 3, observe=observe)
        state["closing"] = True
        closing = asyncio.ensure_future(b.close())
        while not b._task.cancelling():
            await asyncio.sleep(0)
        eng.gate.set()
        await asyncio.wait_for(closing, 5)
        with pytest.raises(Unavailable, match="the batcher failed"):
            await asyncio.wait_for(running, 5)
        return b.healthy

    assert run(main()) is False
