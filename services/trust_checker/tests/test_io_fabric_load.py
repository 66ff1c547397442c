"""The fabric transport under load, on the in-memory fabric (deterministic: a burst
published without yielding is all queued before the transport runs). The same code
path over real Zenoh is covered by test_io_fabric.py."""

from __future__ import annotations

import logging

import anyio
import pytest
from rap_schemas import Stage, StageTrace, keys
from rap_sdk import Sealer
from rap_sdk.fabric.memory import MemoryBus, MemoryFabric
from rap_sdk.inbox import InboxStats
from trust_checker.config import FabricConfig, ServiceConfig
from trust_checker.io.fabric import MAX_BATCH, FabricTransport
from trust_checker.io.session import Session
from trust_checker.service import open_service

from services.trust_checker.tests.io_support import FakeRunner, FakeSpec, fake_loader

pytestmark = pytest.mark.anyio

SYS = "load"


def record(i: int) -> StageTrace:
    return StageTrace(
        node="analysis",
        handler="detect",
        phase="start",
        trigger=b"\x01" * 16,
        trigger_key=keys.event(SYS, "new-data"),
        cycle=i.to_bytes(16, "big"),
        ts=1,
        stage=Stage.ANALYSE,
    )


async def burst(n: int, config: FabricConfig) -> tuple[FakeRunner, Session, FabricTransport]:
    """``n`` trace records published in one go (no yield between them), then taken."""
    mon = FakeRunner(FakeSpec(("cycle",), ("s",)))
    bus = MemoryBus()
    sealer = Sealer("analysis")
    key = keys.trace(SYS, "analysis")
    async with (
        MemoryFabric(bus=bus) as robot,
        MemoryFabric(bus=bus) as fab,
        open_service(ServiceConfig(fabric=config), mon, fabric=fab, loader=fake_loader) as service,
    ):
        assert service.fabric is not None
        for i in range(n):
            await robot.publish(key, sealer.seal_message(key, record(i))[0])
        with anyio.fail_after(10):
            await anyio.wait_all_tasks_blocked()  # the transport took all it could
            await service.session.wait_idle()
    return mon, service.session, service.fabric


async def test_a_burst_is_taken_whole_in_order_in_batches(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    sizes: list[int] = []
    real = Session.submit_many

    async def spy(self: Session, arrivals: list[object]) -> None:
        sizes.append(len(arrivals))
        await real(self, arrivals)  # type: ignore[arg-type]

    monkeypatch.setattr(Session, "submit_many", spy)
    n = 2 * MAX_BATCH + 88
    mon, session, transport = await burst(n, FabricConfig(system=SYS))
    assert [v["cycle"] for v, _ in mon.steps] == [i.to_bytes(16, "big").hex() for i in range(n)]
    assert session.stats.ticks == n
    assert transport.stats.lost == 0
    assert sizes == [MAX_BATCH, MAX_BATCH, 88]  # three hand-offs, not n


async def test_samples_dropped_by_a_full_inbox_are_counted_and_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.ERROR, logger="trust_checker.io.fabric"):
        mon, session, transport = await burst(40, FabricConfig(system=SYS, inbox=16))
    assert session.stats.ticks == 16  # the first 16 waited; the rest found it full
    assert [v["cycle"] for v, _ in mon.steps] == [i.to_bytes(16, "big").hex() for i in range(16)]
    assert transport.stats.lost == 24
    (msg,) = [r.getMessage() for r in caplog.records]
    assert "24 input samples lost (24 in all; last on rap/load/**)" in msg
    assert "verdicts from here on judge a trace with records missing" in msg


async def test_losses_are_logged_at_most_once_a_second_and_all_counted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    class Sub:
        key_expr = "rap/load/**"
        stats = InboxStats()

    config = ServiceConfig(fabric=FabricConfig(system=SYS))
    runner = FakeRunner(FakeSpec(("a",), ("s",)))
    async with (
        MemoryFabric() as fab,
        open_service(config, runner, fabric=fab, loader=fake_loader) as service,
    ):
        transport = service.fabric
        assert transport is not None
        sub = Sub()
        with caplog.at_level(logging.ERROR, logger="trust_checker.io.fabric"):
            for dropped in (3, 3, 10, 12):
                sub.stats.dropped = dropped
                transport._gaps(sub)  # type: ignore[arg-type]
    assert transport.stats.lost == 12
    (msg,) = [r.getMessage() for r in caplog.records]  # the later ones within the second
    assert msg.startswith("fabric: 3 input samples lost (3 in all")
