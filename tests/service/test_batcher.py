"""MicroBatcher alone, with a recording engine: batch bounds, waiting, cancellation, failures."""

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor

import pytest

from gmt.service.batcher import MicroBatcher


class RecordingEngine:
    """Answers each observation with itself; records batch sizes; can be held at a gate or made to fail."""

    def __init__(self) -> None:
        self.batches: list[list] = []
        self.gate = threading.Event()
        self.gate.set()
        self.entered = threading.Event()
        self.fail = False
        self.threads: list[str] = []

    def act(self, contexts, observations, prepared=False):
        self.threads.append(threading.current_thread().name)
        self.entered.set()
        self.gate.wait(30)
        self.batches.append(list(observations))
        if self.fail:
            raise RuntimeError("boom")
        return list(observations)


def run(coro):
    return asyncio.run(coro)


@pytest.fixture
def pool():
    with ThreadPoolExecutor(1) as p:
        yield p


def test_batches_never_exceed_max_batch(pool):
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=2, max_wait_s=0.05, expected=lambda: 5)
        b.start()
        out = await asyncio.gather(*(b.act(None, i) for i in range(5)))
        await b.close()
        return out

    assert run(main()) == [0, 1, 2, 3, 4]
    assert [len(x) for x in eng.batches] == [2, 2, 1]


def test_waits_for_expected_sessions_then_stops_waiting(pool):
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=10, expected=lambda: 3)
        b.start()
        futs = [asyncio.ensure_future(b.act(None, x)) for x in ("a", "b", "c")]
        out = await asyncio.wait_for(asyncio.gather(*futs), 5)  # far less than max_wait_s
        await b.close()
        return out

    assert run(main()) == ["a", "b", "c"]
    assert eng.batches == [["a", "b", "c"]]


def test_wait_is_bounded(pool):
    eng = RecordingEngine()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=0.01, expected=lambda: 100)
        b.start()
        out = await asyncio.wait_for(b.act(None, 1), 5)
        await b.close()
        return out

    assert run(main()) == 1 and eng.batches == [[1]]


def test_cancelled_request_is_dropped_before_the_forward(pool):
    eng = RecordingEngine()
    expected = [5]

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=10, expected=lambda: expected[0])
        b.start()
        doomed = asyncio.ensure_future(b.act(None, "doomed"))
        kept = asyncio.ensure_future(b.act(None, "kept"))
        while b._live() < 2:  # both queued; the batcher waits for 5
            await asyncio.sleep(0)
        doomed.cancel()
        expected[0] = 2  # "kept" and "last" complete the batch, unless "doomed" still counts
        last = asyncio.ensure_future(b.act(None, "last"))
        out = await asyncio.wait_for(asyncio.gather(kept, last), 5)
        await b.close()
        return out

    assert run(main()) == ["kept", "last"]
    assert eng.batches == [["kept", "last"]]


def test_requests_arriving_during_a_forward_form_the_next_batch(pool):
    eng = RecordingEngine()
    eng.gate.clear()

    async def main():
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=0, expected=lambda: 1)
        b.start()
        first = asyncio.ensure_future(b.act(None, 0))
        assert await asyncio.to_thread(eng.entered.wait, 5)  # the forward of [0] is running, held at the gate
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
        b = MicroBatcher(eng, pool, max_batch=64, max_wait_s=0, expected=lambda: 1)
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

        async def gather_once_broken():
            if crashes:
                raise crashes.pop()
            await real_gather()

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
    """With `inline_alone`, a batch of one whose model has no other session runs on the event loop's thread
    (no hop); with several sessions, or without the option, the forward runs in the executor."""
    eng = RecordingEngine()
    live = {"n": 1}

    async def main():
        b = MicroBatcher(
            eng, pool, max_batch=8, max_wait_s=0.5, expected=lambda: live["n"], inline_alone=inline_alone
        )
        b.start()
        assert await b.act(None, "alone") == "alone"
        live["n"] = 2
        assert await asyncio.gather(b.act(None, "x"), b.act(None, "y")) == ["x", "y"]
        await b.close()
        return threading.current_thread().name

    loop_thread = run(main())
    assert eng.threads[0] == loop_thread if inline_alone else eng.threads[0] != loop_thread
    assert eng.threads[1] != loop_thread
    assert eng.batches == [["alone"], ["x", "y"]]
