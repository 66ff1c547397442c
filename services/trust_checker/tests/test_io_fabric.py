"""The checker on the fabric, end to end over real Zenoh sessions on loopback: trace
records and events in, sealed TrustOutput out, hot swap through the admin queryable."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import anyio
import msgspec
import pytest
from rap_schemas import (
    Empty,
    KnowledgeAccess,
    Pose2D,
    Stage,
    StageTrace,
    TrustOutput,
    TrustSpecStatus,
    TrustSpecUpdate,
    Verdict,
    keys,
)
from rap_sdk import Sealer, ZenohConfig, ZenohFabric
from rap_sdk.envelope import typed_decoder
from rap_sdk.fabric import free_port
from trust_checker.config import FabricConfig, FabricInput, ServiceConfig
from trust_checker.io.fabric import FabricTransport, event_stream_name
from trust_checker.io.session import Session
from trust_checker.service import open_service

from services.trust_checker.tests.io_support import (
    FakeRunner,
    FakeSpec,
    RecordingSink,
    fake_loader,
)

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh]

SYS = "tc"
CYCLE = bytes(range(16))
_open_output = typed_decoder(TrustOutput)
_open_status = typed_decoder(TrustSpecStatus)


class Peer:
    def __init__(self, fabric: ZenohFabric) -> None:
        self.fabric = fabric
        self.sealer = Sealer("robot")
        self.outputs: list[TrustOutput] = []
        self.sources: list[str] = []
        self.changed = anyio.Event()

    async def collect(self, sub: Any) -> None:
        async for sample in sub:
            env = _open_output(sample.payload)
            assert env.type == TrustOutput.TYPE
            assert sample.key == keys.trust(SYS, env.body.stream)
            self.outputs.append(env.body)
            self.sources.append(env.source)
            self.changed.set()

    async def wait(self, n: int, timeout: float = 5.0) -> list[TrustOutput]:
        with anyio.fail_after(timeout):
            while len(self.outputs) < n:
                self.changed = anyio.Event()
                await self.changed.wait()
        return self.outputs

    async def send(self, key: str, message: Any, *, cycle: bytes | None = CYCLE) -> None:
        payload, _ = self.sealer.seal_message(key, message, cycle=cycle)
        await self.fabric.publish(key, payload)


def trace(
    phase: str, stage: Stage | None = Stage.ANALYSE, ok: bool = True, sent: list[str] | None = None
) -> StageTrace:
    return StageTrace(
        node="analysis",
        handler="detect",
        phase=phase,  # type: ignore[arg-type]
        trigger=b"\x01" * 16,
        trigger_key=keys.event(SYS, "new-data"),
        cycle=CYCLE,
        ts=1,
        stage=stage,
        ok=ok,
        sent=sent or [],
    )


@asynccontextmanager
async def checker(
    runner: Any, config: FabricConfig | None = None
) -> AsyncIterator[tuple[Session, FabricTransport, Peer, RecordingSink]]:
    port = free_port()
    sink = RecordingSink()
    service_config = ServiceConfig(fabric=config or FabricConfig(system=SYS))
    async with (
        ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"])) as fab,
        ZenohFabric(ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as peer_fab,
        open_service(
            service_config, runner, fabric=fab, sinks=[sink], loader=fake_loader
        ) as service,
        anyio.create_task_group() as tg,
    ):
        transport = service.fabric
        assert transport is not None
        peer = Peer(peer_fab)
        sub = peer_fab.subscribe(keys.pattern(SYS, keys.Kind.TRUST))
        tg.start_soon(peer.collect, sub)
        for key in transport.key_exprs:
            probe = key.replace("**", "probe")
            await peer_fab.wait_matched(probe)
        await fab.wait_matched(keys.trust(SYS, "probe"))
        try:
            yield service.session, transport, peer, sink
        finally:
            sub.close()
            tg.cancel_scope.cancel()


async def test_trace_records_and_events_by_default() -> None:
    ins = (
        "stage",
        "phase",
        "node",
        "cycle",
        "ok",
        "acted",
        "analyse_start",
        "analyse_end",
        "kb_op",
        "kb_key",
        "kb_node",
        "kb_write",
        "kb_read",
        "kb_cycle",
        "event",
        "ev_cycle",
        "ev_new_plan",
        "verdict_approved",
        "verdict_plan",
        "handler",
    )
    mon = FakeRunner(FakeSpec(ins, ("s",)))
    async with checker(mon) as (session, transport, peer, _sink):
        await peer.send(keys.trace(SYS, "analysis"), trace("start"))
        await peer.send(
            keys.trace(SYS, "analysis"),
            trace("end", ok=False, sent=[keys.event(SYS, "anomaly"), keys.data(SYS, "tb1/x")]),
        )
        await peer.send(keys.trace(SYS, "sim"), trace("end", stage=None))
        access = KnowledgeAccess(
            node="plan", op="write", key="plan/x", version=3, ts=1, cycle=CYCLE
        )
        await peer.send(keys.trace(SYS, "plan"), access)
        outside = KnowledgeAccess(node="plan", op="read", key="plan/x", version=3, ts=1)
        await peer.send(keys.trace(SYS, "plan"), outside, cycle=None)  # outside a handler
        await peer.send(keys.event(SYS, "new-plan"), Empty())
        verdict = Verdict(plan_uid=b"\xab" * 16, approved=True, legitimator="l", ts=1)
        await peer.send(keys.event(SYS, "verdict"), verdict)
        await peer.send(keys.data(SYS, "scan"), Empty())  # not read by default
        outs = await peer.wait(7)
        await session.wait_idle()
    hexc = CYCLE.hex()
    steps = [values for values, _ts in mon.steps]
    assert steps == [
        {
            "stage": "analyse",
            "phase": "start",
            "node": "analysis",
            "handler": "detect",
            "cycle": hexc,
            "ok": True,
            "acted": False,
            "analyse_start": hexc,
        },
        {
            "stage": "analyse",
            "phase": "end",
            "node": "analysis",
            "handler": "detect",
            "cycle": hexc,
            "ok": False,
            "acted": True,  # it published on a data topic
            "analyse_end": hexc,
        },
        {  # a node without a stage: stage "" and no <stage>_<phase>
            "stage": "",
            "phase": "end",
            "node": "analysis",
            "handler": "detect",
            "cycle": hexc,
            "ok": True,
            "acted": False,
        },
        {
            "kb_op": "write",
            "kb_key": "plan/x",
            "kb_node": "plan",
            "kb_write": "plan/x",
            "kb_cycle": hexc,
        },
        {
            "kb_op": "read",
            "kb_key": "plan/x",
            "kb_node": "plan",
            "kb_read": "plan/x",
            "kb_cycle": "",
        },
        {"event": "new-plan", "ev_cycle": hexc, "ev_new_plan": hexc},
        {
            "event": "verdict",
            "ev_cycle": hexc,
            "verdict_approved": True,
            "verdict_plan": "ab" * 16,
        },
    ]
    assert all(isinstance(ts, int) and ts > 0 for _v, ts in mon.steps)
    assert [(o.stream, o.tick) for o in outs] == [("s", i) for i in range(7)]
    assert peer.sources == ["trust_checker"] * 7
    assert transport.stats.rejections.total == 0


async def test_a_message_setting_no_declared_input_is_not_a_tick() -> None:
    mon = FakeRunner(FakeSpec(("ev_new_plan",), ("s",)))
    async with checker(mon) as (session, _t, peer, sink):
        await peer.send(keys.trace(SYS, "analysis"), trace("start"))
        await peer.send(keys.event(SYS, "new-plan"), Empty(), cycle=None)
        await peer.wait(1)
        await session.wait_idle()
    assert session.stats.ignored == 1
    assert len(mon.steps) == 1
    ((values, _ts),) = mon.steps
    assert set(values) == {"ev_new_plan"}  # a root event: its own uid is the cycle
    assert len(sink.outs) == 1


async def test_an_input_the_runner_refuses_is_counted() -> None:
    explicit = {"x": FabricInput(keys.data(SYS, "pose"), field="x")}
    config = FabricConfig(system=SYS, inputs=explicit)  # one subscription: ordered
    mon = FakeRunner(FakeSpec(("x", "ev_go"), ("s",)))
    async with checker(mon, config) as (session, transport, peer, _sink):
        assert transport.key_exprs == [keys.system_pattern(SYS)]
        await peer.send(keys.data(SYS, "pose"), Pose2D(x=3.0, y=0.0, theta=0.0))
        await peer.send(keys.event(SYS, "go"), Empty())
        outs = await peer.wait(1)
    # the fake refuses a Float: an InputError, counted; the next message ticks
    assert session.stats.input_errors == 1
    assert [o.tick for o in outs] == [0]  # a refused input takes no tick


async def test_explicit_inputs_whole_body_or_one_field() -> None:
    explicit = {
        "verdict": FabricInput(keys.event(SYS, "verdict")),
        "ok": FabricInput(keys.event(SYS, "verdict"), field="approved"),
        "missing": FabricInput(keys.data(SYS, "pose"), field="nope"),
    }
    config = FabricConfig(system=SYS, inputs=explicit, default_inputs=False)
    mon = FakeRunner(FakeSpec(("ok", "missing", "bottom_in"), ("s",)))
    async with checker(mon, config) as (session, transport, peer, _sink):
        assert transport.key_exprs == [keys.event(SYS, "verdict"), keys.data(SYS, "pose")]
        verdict = Verdict(plan_uid=b"\x01" * 16, approved=False, legitimator="l", ts=1)
        await peer.send(keys.data(SYS, "pose"), Pose2D(x=1.0, y=2.0, theta=0.0))
        await peer.send(keys.event(SYS, "verdict"), verdict)
        outs = await peer.wait(1)
        await session.wait_idle()
    # the pose has no field "nope"
    assert transport.stats.rejections.by_reason == {
        "rap.PoseND/N: stream 'missing' reads field 'nope', which the body does not have": 1
    }
    assert mon.steps[0][0] == {"ok": False}
    assert outs[0].value == 0
    assert outs[0].deferred is False


async def test_bottom_is_published_as_deferred() -> None:
    explicit = {"a": FabricInput(keys.data(SYS, "a"), field="s")}
    config = FabricConfig(system=SYS, inputs=explicit, default_inputs=False)
    mon = FakeRunner(FakeSpec(("a",), ("s",)))

    class Text(msgspec.Struct, frozen=True):
        s: str

    async with checker(mon, config) as (_session, _t, peer, _sink):
        payload, _ = peer.sealer.seal(
            keys.data(SYS, "a"), "t.Text/1", msgspec.msgpack.encode(Text("bottom"))
        )
        await peer.fabric.publish(keys.data(SYS, "a"), payload)
        outs = await peer.wait(1)
    assert outs[0].deferred is True
    assert outs[0].value is None


async def test_bad_samples_are_rejected_and_counted() -> None:
    mon = FakeRunner(FakeSpec(("ev_x",), ("s",)))
    async with checker(mon) as (session, transport, peer, _sink):
        await peer.fabric.publish(keys.event(SYS, "x"), b"not an envelope")
        payload, _ = peer.sealer.seal(keys.trace(SYS, "n"), StageTrace.TYPE, b"\x01")
        await peer.fabric.publish(keys.trace(SYS, "n"), payload)
        await peer.send(keys.event(SYS, "x"), Empty())
        await peer.wait(1)
        await session.wait_idle()
    assert transport.stats.rejections.total == 2
    assert len(mon.steps) == 1


async def test_hot_swap_through_the_admin_queryable() -> None:
    mon = FakeRunner(FakeSpec(("ev_a",), ("s",)))
    async with checker(mon) as (session, transport, peer, _sink):
        await peer.send(keys.event(SYS, "a"), Empty())
        await peer.wait(1)
        swap_key = keys.admin(SYS, "trust_checker", "swap")
        assert transport.swap_key == swap_key
        await peer.fabric.wait_matched(swap_key, queryable=True)

        async def swap(text: str) -> TrustSpecStatus:
            payload, _ = peer.sealer.seal_message(swap_key, TrustSpecUpdate(spec=text))
            (reply,) = await peer.fabric.query(swap_key, payload, timeout=5.0)
            assert reply.ok, reply.payload
            env = _open_status(reply.payload)
            assert env.source == "trust_checker"
            body: TrustSpecStatus = env.body
            return body

        bad = await swap("in ev_b\nwhat is this\n")
        assert not bad.ok
        assert bad.problems[0].startswith("<swap>:2:1:")
        await peer.send(keys.event(SYS, "a"), Empty())  # the old spec still runs
        await peer.wait(2)
        good = await swap(f"in {event_stream_name('b-c')}\nout t\n")
        assert good.ok
        assert good.inputs == ["ev_b_c"]
        await peer.send(keys.event(SYS, "b-c"), Empty())
        outs = await peer.wait(3)
        (err,) = await peer.fabric.query(swap_key, b"junk", timeout=5.0)
        assert not err.ok
        assert b"swap request refused" in err.payload
    assert [(o.stream, o.tick) for o in outs] == [("s", 0), ("s", 1), ("t", 2)]
    assert session.stats.swaps == 1
    assert session.stats.swaps_rejected == 1


# -- with the real runner and parser -----------------------------------------------------


async def test_real_runner_on_trace_records_and_swap() -> None:
    from trust_checker.io.specs import load_text

    spec = "in ok: Bool\nin analyse_start: Str\nout failed: Bool\nfailed = !ok\n"
    port = free_port()
    config = ServiceConfig(node="tc1", verdicts=False, fabric=FabricConfig(system=SYS))
    async with (
        ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"])) as fab,
        ZenohFabric(ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as peer_fab,
        open_service(config, load_text(spec), fabric=fab),
        anyio.create_task_group() as tg,
    ):
        peer = Peer(peer_fab)
        sub = peer_fab.subscribe(keys.pattern(SYS, keys.Kind.TRUST))
        tg.start_soon(peer.collect, sub)
        await peer_fab.wait_matched(keys.trace(SYS, "analysis"))
        await fab.wait_matched(keys.trust(SYS, "failed"))
        await peer.send(keys.trace(SYS, "analysis"), trace("start"))
        await peer.send(keys.trace(SYS, "analysis"), trace("end", ok=False))
        await peer.wait(2)
        swap_key = keys.admin(SYS, "tc1", "swap")
        await peer_fab.wait_matched(swap_key, queryable=True)
        new = "in ok: Bool\nout was: Bool\nwas = ok[-1, true]\n"
        payload, _ = peer.sealer.seal_message(swap_key, TrustSpecUpdate(spec=new))
        (reply,) = await peer_fab.query(swap_key, payload, timeout=5.0)
        assert _open_status(reply.payload).body.ok
        await peer.send(keys.trace(SYS, "analysis"), trace("start"))
        outs = await peer.wait(3)
        sub.close()
        tg.cancel_scope.cancel()
    assert [(o.stream, o.tick, o.value) for o in outs] == [
        ("failed", 0, False),
        ("failed", 1, True),
        ("was", 2, False),  # ok one tick back, from before the swap
    ]
    assert all(o.ts > 0 for o in outs)
