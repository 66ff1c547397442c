"""Tick policies and the session that owns the spec runner (with a hand-written runner)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import pytest
from trust_checker.config import ServiceConfig
from trust_checker.io.session import Session
from trust_checker.io.ticks import (
    MESSAGE,
    Arrival,
    TickPolicy,
    merge,
    parse_duration,
    parse_tick_policy,
)
from trust_checker.service import open_service
from trust_checker.values import BOTTOM

from services.trust_checker.tests.io_support import (
    FakeRunner,
    FakeSpec,
    RecordingSink,
    fake_loader,
)


class StepClock:
    """A wall clock the test moves."""

    def __init__(self, start: int = 1_000_000_000) -> None:
        self.now = start

    def time_ns(self) -> int:
        self.now += 1000
        return self.now


# -- pure parts ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "policy"),
    [
        ("message", MESSAGE),
        ("window:10ms", TickPolicy("window", 10_000_000)),
        ("window:1.5s", TickPolicy("window", 1_500_000_000)),
        ("window:200us", TickPolicy("window", 200_000)),
        (" window:500ns ", TickPolicy("window", 500)),
    ],
)
def test_parse_tick_policy(text: str, policy: TickPolicy) -> None:
    assert parse_tick_policy(text) == policy


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("burst", "unknown tick policy"),
        ("window", "unknown tick policy"),
        ("window:10", "not a duration"),
        ("window:0ms", "above 0"),
        ("window:2min", "not a duration"),
        ("window:61s", "at most 60s"),
    ],
)
def test_bad_tick_policy(text: str, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        parse_tick_policy(text)


def test_parse_duration() -> None:
    assert parse_duration("10ms") == 10_000_000
    assert parse_duration("2s") == 2_000_000_000


def test_merge_keeps_the_last_value_per_stream_and_the_first_time() -> None:
    tick = merge(
        [
            Arrival({"a": 1}, 10, "t/a"),
            Arrival({"b": 2, "a": 3}, 20, "t/b"),
            Arrival({"a": 4}, 30, "t/a"),
        ]
    )
    assert tick.values == {"a": 4, "b": 2}
    assert tick.ts_ns == 10
    assert tick.count == 3
    assert tick.origin == "t/a,t/b"
    with pytest.raises(ValueError, match="at least one"):
        merge([])


# -- the session --------------------------------------------------------------------------


@asynccontextmanager
async def running(
    runner: FakeRunner, tick: str = "message", clock: StepClock | None = None
) -> AsyncIterator[tuple[Session, RecordingSink]]:
    """A checker with no transport (fed through its session), as open_service wires it."""
    sink = RecordingSink()
    config = ServiceConfig(tick=tick)
    async with open_service(
        config, runner, sinks=[sink], loader=fake_loader, clock=clock
    ) as service:
        yield service.session, sink


pytestmark = pytest.mark.anyio


async def test_one_message_one_tick_with_timestamps() -> None:
    mon = FakeRunner(FakeSpec(("a", "b"), ("s",)))
    clock = StepClock()
    async with running(mon, clock=clock) as (session, sink):
        for i, name in enumerate(["a", "b", "a"]):
            await session.submit(Arrival({name: i + 1}, clock.time_ns(), name))
        await session.wait_idle()
    assert [o.value for o in sink.outs] == [1, 3, 6]
    assert [o.tick for o in sink.outs] == [0, 1, 2]
    stamps = [ts for _, ts in mon.steps]
    assert all(isinstance(ts, int) for ts in stamps)
    assert stamps == sorted(stamps)
    assert session.stats.ticks == 3


async def test_a_message_setting_no_input_is_not_a_tick() -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    async with running(mon) as (session, sink):
        await session.submit(Arrival({"zzz": 1}, 1, "x"))
        await session.submit(Arrival({"a": 2, "zzz": 5}, 2, "x"))
        await session.wait_idle()
    assert mon.steps == [({"a": 2}, 2)]  # only declared inputs reach the runner
    assert session.stats.ignored == 1
    assert [o.value for o in sink.outs] == [2]


async def test_window_merges_a_burst_into_one_atomic_tick() -> None:
    mon = FakeRunner(FakeSpec(("a", "b"), ("s",)))
    async with running(mon, "window:300ms") as (session, sink):
        await session.submit(Arrival({"a": 1}, 100, "a"))
        await session.submit(Arrival({"b": 10}, 200, "b"))
        await session.submit(Arrival({"a": 2}, 300, "a"))
        await sink.wait_for(1)
        await session.submit(Arrival({"b": 100}, 400, "b"))
        await sink.wait_for(2)
    assert mon.steps == [({"a": 2, "b": 10}, 100), ({"b": 100}, 400)]
    assert [o.value for o in sink.outs] == [12, 112]


async def test_bad_input_and_failing_tick_are_counted_and_the_next_one_works() -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    async with running(mon) as (session, sink):
        await session.submit(Arrival({"a": 1.5}, 1, "a"))  # the fake takes Int only
        await session.submit(Arrival({"a": "boom"}, 2, "a"))
        await session.submit(Arrival({"a": 4}, 3, "a"))
        await session.wait_idle()
    assert session.stats.input_errors == 1
    assert session.stats.eval_errors == 1
    assert [o.value for o in sink.outs] == [4]


async def test_bottom_reaches_the_sinks() -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    async with running(mon) as (session, sink):
        await session.submit(Arrival({"a": "bottom"}, 1, "a"))
        await session.wait_idle()
    assert [o.value for o in sink.outs] == [BOTTOM]


async def test_swap_carries_history_and_a_bad_spec_keeps_the_old_one() -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    async with running(mon) as (session, sink):
        await session.submit(Arrival({"a": 5}, 1, "a"))
        bad = await session.request_swap("in a\nnonsense here\n", path="new.dsrv")
        assert not bad.ok
        assert bad.problems[0].startswith("new.dsrv:2:1: unexpected")
        await session.submit(Arrival({"a": 1}, 2, "a"))
        good = await session.request_swap("in a c\nout t\n")
        assert good.ok
        assert good.inputs == ["a", "c"]
        assert good.outputs == ["t"]
        assert good.tick == 2
        await session.submit(Arrival({"c": 4}, 3, "c"))
        await session.wait_idle()
    assert [(o.stream, o.value) for o in sink.outs] == [("s", 5), ("s", 6), ("t", 10)]
    assert [s.ok for s in sink.statuses] == [False, True]
    assert session.stats.swaps == 1
    assert session.stats.swaps_rejected == 1


async def test_a_swap_ends_a_window_burst_after_its_tick() -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    async with running(mon, "window:2s") as (session, sink):
        await session.submit(Arrival({"a": 1}, 1, "a"))
        status = await session.request_swap("in a\nout t\n", timeout=1.0)
        assert status.ok
        await sink.wait_for(1)
    assert [(o.stream, o.value) for o in sink.outs] == [("s", 1)]


async def test_periodic_outputs_tick_without_inputs() -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",), period_ns=20_000_000))
    async with running(mon) as (session, sink):
        await sink.wait_for(3, timeout=5)
    assert session.stats.periodic_ticks >= 3
    periodic = [ts for values, ts in mon.steps if not values]
    assert len(periodic) >= 3
    assert all(ts is not None and ts % 20_000_000 == 0 for ts in periodic)
    assert periodic == sorted(periodic)


async def test_a_batch_is_one_arrival_each_in_order() -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    async with running(mon) as (session, sink):
        await session.submit_many([Arrival({"a": i}, i, "a") for i in range(1, 5)])
        await session.submit_many([Arrival({}, 9, "x")])  # sets nothing: not submitted
        await session.submit(Arrival({"a": 10}, 10, "a"))
        await session.wait_idle()
    assert [v["a"] for v, _ in mon.steps] == [1, 2, 3, 4, 10]
    assert [o.value for o in sink.outs] == [1, 3, 6, 10, 20]
    assert session.stats.messages == 5


async def test_a_window_burst_spans_batches_and_a_swap_follows_the_batch() -> None:
    mon = FakeRunner(FakeSpec(("a", "b"), ("s",)))
    async with running(mon, "window:300ms") as (session, sink):
        await session.submit_many([Arrival({"a": 1}, 100, "a"), Arrival({"b": 10}, 200, "b")])
        await session.submit_many([Arrival({"a": 2}, 300, "a")])
        status = await session.request_swap("in a b\nout t\n", timeout=2.0)
        assert status.ok
        await sink.wait_for(1)
    # one atomic tick of the whole burst, then the swap (the old spec's output)
    assert mon.steps == [({"a": 2, "b": 10}, 100)]
    assert [(o.stream, o.value) for o in sink.outs] == [("s", 12)]
