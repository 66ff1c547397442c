"""The bridge contract, against every protocol (the harness: contract.py)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import anyio
import pytest
from anyio.abc import TaskGroup
from rap_bridges import HEADER_CAUSE, HEADER_CYCLE, Frame

from libs.rap_bridges.tests.contract import (
    PROTOCOLS,
    TIMEOUT,
    FabricSide,
    bridge,
    fabric_side,
    json_frame,
    numbers,
    outside_factory,
    outside_of,
    require_server,
    until,
)

pytestmark = [pytest.mark.anyio]

CYCLE = bytes(range(16))
CAUSE = bytes(range(16, 32))


@pytest.fixture(params=PROTOCOLS)
def protocol(request: pytest.FixtureRequest) -> str:
    return str(request.param)


class Rig:
    def __init__(self, tg: TaskGroup, side: FabricSide, outside: Any) -> None:
        self.tg = tg
        self.side = side
        self.outside = outside


@pytest.fixture
async def rig(protocol: str, tmp_path: Path) -> AsyncIterator[Rig]:
    require_server(protocol)  # skip (or fail) here: not from inside a task group
    async with anyio.create_task_group() as outer:
        async with fabric_side(outer) as side, outside_of(protocol, tmp_path, outer) as outside:
            async with anyio.create_task_group() as tg:  # the bridges: stopped first
                yield Rig(tg, side, outside)
                tg.cancel_scope.cancel()
        outer.cancel_scope.cancel()


async def test_order_is_kept_out_and_cycle_and_cause_ride_in_headers(rig: Rig) -> None:
    out = rig.outside
    await out.start()
    await out.start_receiver()
    b = bridge(out, rig.side.fabric, "out", buffer=5000)  # the fabric outruns the link
    await rig.tg.start(b.run)
    with anyio.fail_after(10):
        await b.wait_connected()
    await rig.side.publish(-1, cycle=CYCLE, cause=CAUSE)
    for n in range(1000):
        await rig.side.publish(n)
    await out.wait_received(1001)
    assert numbers(out.received) == [-1, *range(1000)]
    first = out.received[0].headers
    assert first[HEADER_CYCLE] == CYCLE.hex()
    assert first[HEADER_CAUSE] == CAUSE.hex()
    assert first["rap-type"] == "test.Reading/1"
    await until(lambda: b.stats.sent == 1001)  # the last confirmation may be on its way
    assert (b.stats.rejected, b.stats.dropped) == (0, 0)


async def test_order_is_kept_in_and_the_bridge_seals(rig: Rig) -> None:
    out = rig.outside
    await out.start()
    b = bridge(out, rig.side.fabric, "in", name="inbound", buffer=5000)
    await rig.tg.start(b.run)
    with anyio.fail_after(10):
        await b.wait_connected()
    frames = [json_frame(0, **{HEADER_CYCLE: CYCLE.hex(), HEADER_CAUSE: CAUSE.hex()})]
    frames += [json_frame(n) for n in range(1, 1000)]
    await out.send(frames)
    await rig.side.wait_for(1000)
    assert rig.side.readings() == list(range(1000))
    env = rig.side.got[0]
    assert (env.source, env.type, env.cycle, env.cause) == (
        "inbound",
        "test.Reading/1",
        CYCLE,
        CAUSE,
    )
    assert [e.seq for e in rig.side.got] == list(range(1000))
    assert (b.stats.received, b.stats.published, b.stats.rejected) == (1000, 1000, 0)


async def test_nothing_is_lost_across_a_server_restart(rig: Rig) -> None:
    """QoS 1: what the fabric sends while the server is down waits in the buffer and
    arrives, in order, once the bridge has reconnected."""
    out = rig.outside
    await out.start()
    await out.start_receiver()
    b = bridge(out, rig.side.fabric, "out", qos=1)
    await rig.tg.start(b.run)
    with anyio.fail_after(10):
        await b.wait_connected()
    for n in range(100):
        await rig.side.publish(n)
    await out.wait_received(100)
    await out.stop()
    with anyio.fail_after(10):
        await b.wait_connected(False)
    for n in range(100, 200):
        await rig.side.publish(n)  # during the outage: buffered
    assert not b.connected
    await out.start()
    with anyio.fail_after(TIMEOUT):  # a Kafka consumer group takes its time to rejoin
        await b.wait_connects(2)
    await out.wait_received(200)
    got = numbers(out.received)
    assert sorted(set(got)) == list(range(200))  # nothing lost
    assert got == sorted(got)  # in order (a resent message would repeat in place)
    assert b.stats.reconnects >= 1
    assert b.stats.disconnects >= 1
    assert b.stats.dropped == 0


async def test_an_in_bridge_reconnects_after_a_restart(rig: Rig) -> None:
    out = rig.outside
    await out.start()
    b = bridge(out, rig.side.fabric, "in")
    await rig.tg.start(b.run)
    with anyio.fail_after(10):
        await b.wait_connected()
    await out.send([json_frame(n) for n in range(10)])
    await rig.side.wait_for(10)
    await out.stop()
    with anyio.fail_after(10):
        await b.wait_connected(False)
    await out.start()
    with anyio.fail_after(TIMEOUT):  # a Kafka consumer group takes its time to rejoin
        await b.wait_connects(2)
    await out.send([json_frame(n) for n in range(10, 20)])
    await until(lambda: set(range(20)) <= set(rig.side.readings()))
    got = rig.side.readings()
    assert got[:10] == list(range(10))
    # at least once: a broker may deliver again what it had delivered before its restart
    # (mosquitto does, from its persisted sessions); the new messages come once, in order
    assert [n for n in got[10:] if n >= 10] == list(range(10, 20))
    assert b.stats.reconnects >= 1


async def test_malformed_input_is_rejected_and_counted_and_the_bridge_goes_on(
    rig: Rig,
) -> None:
    out = rig.outside
    await out.start()
    b = bridge(out, rig.side.fabric, "in")
    await rig.tg.start(b.run)
    with anyio.fail_after(10):
        await b.wait_connected()
    bad = [
        Frame(b"\xff\x00 not json"),
        Frame(b'{"n": "three"}'),  # the wrong type of field
        Frame(b'{"note": "no n"}'),  # a required field missing
        json_frame(7, **{HEADER_CYCLE: "not-hex"}),
        json_frame(8, **{"rap-type": "rap.Pose2D/1"}),  # another message
        Frame(b"[" * 10_000),  # deeply nested
    ]
    await out.send([json_frame(0), *bad, json_frame(1)])
    await rig.side.wait_for(2)
    await until(lambda: b.stats.rejected >= len(bad))
    assert rig.side.readings() == [0, 1]
    assert b.stats.rejected == len(bad)
    assert b.connected
    reasons = " | ".join(b.stats.rejections.by_reason)
    assert "test.Reading/N JSON" in reasons
    assert "rap-cycle" in reasons
    assert "expected type test.Reading/N" in reasons


@pytest.mark.parametrize(
    ("overflow", "kept"), [("drop-oldest", range(15, 25)), ("drop-newest", range(10))]
)
async def test_the_overflow_policy_drops_exactly_what_it_says(
    rig: Rig, overflow: str, kept: range
) -> None:
    """The server is down: 25 messages meet a buffer of 10; 15 are dropped and
    counted, and the 10 the policy keeps arrive once the server is there."""
    out = rig.outside
    await out.start()
    await out.start_receiver()  # (MQTT: the receiver's session, kept across the restart)
    await out.stop()
    b = bridge(out, rig.side.fabric, "out", buffer=10, overflow=overflow)
    await rig.tg.start(b.run)
    for n in range(25):
        await rig.side.publish(n)
    assert b.stats.dropped == 15
    assert not b.connected
    await out.start()
    await out.wait_received(10)
    await anyio.sleep(0.2)  # nothing more comes
    assert numbers(out.received) == list(kept)
    assert b.stats.sent == 10
    assert b.stats.dropped == 15


async def test_the_block_policy_makes_the_publisher_wait(rig: Rig) -> None:
    """A full buffer with ``block``: a publisher on this fabric waits for room (nothing
    dropped), and goes on once the link drains the buffer."""
    out = rig.outside
    await out.start()
    await out.start_receiver()
    await out.stop()
    b = bridge(out, rig.side.fabric, "out", buffer=3, overflow="block")
    await rig.tg.start(b.run)
    for n in range(3):
        await rig.side.publish(n)
    with anyio.move_on_after(0.3) as waited:
        await rig.side.publish(3)
    assert waited.cancelled_caught  # the publisher waited for room
    assert b.stats.dropped == 0
    await out.start()
    with anyio.fail_after(10):
        await rig.side.publish(3)  # room comes as the bridge sends
    await out.wait_received(4)
    assert numbers(out.received) == [0, 1, 2, 3]
    assert b.stats.dropped == 0


def test_the_suite_covers_every_protocol() -> None:
    """Every protocol a spec accepts has an outside for the contract (and a link)."""
    from rap_bridges.core import _BUILT_IN
    from rap_bridges.spec import PROTOCOLS as KNOWN

    for protocol in KNOWN:
        assert protocol in _BUILT_IN, protocol
        assert outside_factory(protocol) is not None
