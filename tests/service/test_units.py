"""`run_whole`: a change either never happens or completes, whatever its caller does; one that never waits runs
in its caller, without a task of its own."""

import asyncio

import pytest

from gmt.service import units


def test_a_change_that_never_waits_runs_in_its_caller_and_answers():
    async def change():
        assert units.current() is not None and units.current().cancellable
        return asyncio.current_task()

    async def caller():
        me = asyncio.current_task()
        ran_in = await units.run_whole(change())
        return me, ran_in, units.current()

    me, ran_in, after = asyncio.run(caller())
    assert ran_in is me  # no task, no extra turns of the loop
    assert after is None  # the unit is the change's only


def test_an_error_before_the_first_wait_reaches_the_caller():
    async def change():
        raise ValueError("bad observation")

    async def caller():
        await units.run_whole(change())

    with pytest.raises(ValueError, match="bad observation"):
        asyncio.run(caller())


def test_a_change_that_waits_goes_on_in_a_task_with_its_unit_and_answers():
    async def change(gate: asyncio.Event):
        unit = units.current()
        await gate.wait()
        await asyncio.sleep(0)  # a bare yield too
        assert units.current() is unit
        return "done", asyncio.current_task()

    async def caller():
        gate = asyncio.Event()
        asyncio.get_running_loop().call_soon(gate.set)
        result, ran_in = await units.run_whole(change(gate))
        return result, ran_in is asyncio.current_task()

    assert asyncio.run(caller()) == ("done", False)


async def _start_then_give_up(change, reached: asyncio.Event, gate: asyncio.Event) -> None:
    """Run `change()` as one unit, cancel its caller once it has `reached` its wait, then open its `gate`."""
    call = asyncio.ensure_future(units.run_whole(change()))
    await reached.wait()
    call.cancel()
    with pytest.raises(asyncio.CancelledError):
        await call
    gate.set()


def test_a_caller_that_gives_up_before_the_point_of_no_return_drops_the_change():
    async def scenario():
        gate, reached, ended, finished = asyncio.Event(), asyncio.Event(), asyncio.Event(), []

        async def change():
            reached.set()
            try:
                await gate.wait()
                finished.append("completed")
            except asyncio.CancelledError:
                finished.append("cancelled")
                raise
            finally:
                ended.set()

        await _start_then_give_up(change, reached, gate)
        await asyncio.wait_for(ended.wait(), 5)
        return finished

    assert asyncio.run(scenario()) == ["cancelled"]


def test_a_caller_that_gives_up_past_the_point_of_no_return_leaves_the_change_to_complete():
    async def scenario():
        gate, reached, done = asyncio.Event(), asyncio.Event(), asyncio.Event()

        async def change():
            units.point_of_no_return()
            reached.set()
            await gate.wait()
            done.set()

        await _start_then_give_up(change, reached, gate)
        await asyncio.wait_for(done.wait(), 5)  # (raises TimeoutError if the change was dropped)
        return done.is_set()

    assert asyncio.run(scenario())


def test_a_dropped_change_is_marked_dropped_and_one_past_its_point_of_no_return_is_not():
    """`Unit.dropped` tells the batcher not to start anything still queued for a change whose caller gave up (the
    cancellation reaches the change's parts only over the next turns of the loop)."""

    async def scenario(past: bool):
        gate, reached, units_seen = asyncio.Event(), asyncio.Event(), []

        async def change():
            units_seen.append(units.current())
            if past:
                units.point_of_no_return()
            reached.set()
            await gate.wait()

        await _start_then_give_up(change, reached, gate)
        return units_seen[0].dropped

    assert asyncio.run(scenario(past=False)) is True
    assert asyncio.run(scenario(past=True)) is False
