"""Verdicts through the I/O layer: the session, MQTT (a mosquitto of the test's own), the
fabric (real Zenoh sessions on loopback) and the command line's ``--explain``."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiomqtt
import anyio
import msgspec
import pytest
from rap_schemas import Pose2D, TrustOutput, TrustVerdict, keys
from rap_sdk import Sealer, ZenohConfig, ZenohFabric
from rap_sdk.envelope import typed_decoder
from rap_sdk.fabric import free_port
from trust_checker.config import FabricConfig, FabricInput, MqttConfig, ServiceConfig
from trust_checker.io.session import Session
from trust_checker.io.specs import load_text
from trust_checker.service import open_service
from trust_checker.tracefile import read_trace, run_trace

from services.trust_checker.tests.io_support import (
    FakeRunner,
    FakeSpec,
    RecordingSink,
    fake_loader,
    mosquitto,
)

SPEC = """\
in x: Float
out ok: Bool
ok = x < 2.0
trigger x > 5.0 "far out" critical
"""


@dataclass
class VerdictRecorder(RecordingSink):
    got: list[TrustVerdict] = field(default_factory=list)
    order: list[str] = field(default_factory=list)

    async def outputs(self, outs: Sequence[Any]) -> None:
        self.order.append("outputs")
        await super().outputs(outs)

    async def verdicts(self, verdicts: Sequence[TrustVerdict]) -> None:
        self.order.append("verdicts")
        self.got.extend(verdicts)


def summary(v: TrustVerdict) -> tuple[object, ...]:
    return (v.stream, v.tick, v.value, v.kind, v.severity, v.message)


def causes(v: TrustVerdict) -> list[tuple[object, ...]]:
    return [(c.depth, c.expr, c.value, c.input, c.input_tick) for c in v.because]


# -- the session ----------------------------------------------------------------------------


@pytest.mark.anyio
async def test_session_gives_verdicts_after_outputs_and_keeps_explaining_across_a_swap() -> None:
    from trust_checker.io.ticks import Arrival

    sink = VerdictRecorder()
    plain = RecordingSink()  # a sink without verdicts() gets outputs only
    async with open_service(ServiceConfig(), load_text(SPEC), sinks=[sink, plain]) as service:
        session = service.session
        for i, x in enumerate((1.0, 2.5, 3.0, 6.0)):
            await session.submit(Arrival({"x": x}, 1_000 + i, "test"))
        await session.wait_idle()
        status = await session.request_swap(SPEC.replace("2.0", "7.0"))
        assert status.ok
        await session.submit(Arrival({"x": 1.0}, 2_000, "test"))  # tick 4: true
        await session.submit(Arrival({"x": 8.0}, 2_001, "test"))  # tick 5: false again
        await session.wait_idle()
    assert [summary(v) for v in sink.got] == [
        ("ok", 1, False, "output", None, ""),
        ("trigger.0", 3, True, "trigger", "critical", "far out"),
        ("ok", 5, False, "output", None, ""),
        ("trigger.0", 5, True, "trigger", "critical", "far out"),
    ]
    assert causes(sink.got[0]) == [(0, "x", 2.5, "x", 1)]
    assert sink.got[0].ts == 1_001
    assert sink.got[2].expr == "x < 7.0"
    assert sink.order[:3] == ["outputs", "outputs", "verdicts"]
    assert session.stats.verdicts == 4
    assert len(plain.outs) == len(sink.outs) == 6


def test_explain_needs_a_real_runner() -> None:
    with pytest.raises(TypeError, match="needs a trust_checker SpecRunner"):
        Session(FakeRunner(FakeSpec(("a",), ("s",))), loader=fake_loader, explain=True)


# -- MQTT -----------------------------------------------------------------------------------


@pytest.mark.anyio
async def test_mqtt_publishes_verdicts_as_json_on_the_verdict_topic(tmp_path: Path) -> None:
    async with mosquitto(tmp_path) as broker:
        cfg = MqttConfig(port=broker.port, timeout=5.0, verdict_topic="checks/verdicts")
        got: list[tuple[str, Any]] = []
        async with (
            open_service(ServiceConfig(mqtt=cfg), load_text(SPEC)),
            aiomqtt.Client("127.0.0.1", broker.port, timeout=5.0) as client,
        ):
            await client.subscribe("checks/verdicts")
            await client.subscribe("ok")
            for x in ("1.0", '{"Float": 2.5}', "3.0", '{"value": 6.5}'):
                await client.publish("x", x)
            with anyio.fail_after(10):
                async for message in client.messages:
                    got.append((message.topic.value, json.loads(bytes(message.payload))))
                    if len(got) == 6:  # 4 outputs, 2 verdicts
                        break
    verdicts = [p for t, p in got if t == "checks/verdicts"]
    assert [p for t, p in got if t == "ok"] == [{"value": v} for v in (True, False, False, False)]
    ts = verdicts[0].pop("ts")
    assert isinstance(ts, int)
    assert ts > 0
    assert verdicts[0] == {
        "stream": "ok",
        "tick": 1,
        "value": False,
        "expr": "x < 2.0",
        "because": [{"expr": "x", "value": 2.5, "input": "x", "input_tick": 1}],
    }
    verdicts[1].pop("ts")
    assert verdicts[1] == {
        "stream": "trigger.0",
        "tick": 3,
        "value": True,
        "kind": "trigger",
        "expr": "x > 5.0",
        "because": [{"expr": "x", "value": 6.5, "input": "x", "input_tick": 3}],
        "message": "far out",
        "severity": "critical",
    }
    assert msgspec.json.decode(json.dumps(verdicts[1]), type=TrustVerdict).severity == "critical"


@pytest.mark.anyio
async def test_mqtt_verdict_topic_empty_publishes_none(tmp_path: Path) -> None:
    async with mosquitto(tmp_path) as broker:
        cfg = MqttConfig(port=broker.port, timeout=5.0, verdict_topic="")
        recorder = RecordingSink()
        service_config = ServiceConfig(mqtt=cfg)
        async with open_service(service_config, load_text(SPEC), sinks=[recorder]) as service:
            async with aiomqtt.Client("127.0.0.1", broker.port, timeout=5.0) as client:
                await client.publish("x", "1.0")
                await client.publish("x", "9.0")  # ok turns false, the trigger fires
                await recorder.wait_for(n_outs=2)
                await service.session.wait_idle()  # the second tick's sinks are done
    assert service.session.stats.verdicts == 2
    assert service.mqtt is not None
    assert service.mqtt.stats.published == 2  # the two outputs only


# -- the fabric -------------------------------------------------------------------------------

SYS = "tcx"
_open_verdict = typed_decoder(TrustVerdict)
_open_output = typed_decoder(TrustOutput)


@pytest.mark.anyio
@pytest.mark.zenoh
async def test_fabric_publishes_sealed_verdicts_next_to_the_outputs() -> None:
    port = free_port()
    pose = keys.data(SYS, "pose")
    config = ServiceConfig(
        node="tcv",
        fabric=FabricConfig(
            system=SYS, inputs={"x": FabricInput(key=pose, field="x")}, default_inputs=False
        ),
    )
    verdicts: list[tuple[str, str, TrustVerdict]] = []
    outputs: list[tuple[str, TrustOutput]] = []
    done = anyio.Event()
    outputs_done = anyio.Event()

    async def collect_verdicts(sub: Any) -> None:
        async for sample in sub:
            env = _open_verdict(sample.payload)
            verdicts.append((sample.key, env.source, env.body))
            if len(verdicts) == 2:
                done.set()

    async def collect_outputs(sub: Any) -> None:
        async for sample in sub:
            env = _open_output(sample.payload)
            outputs.append((env.type, env.body))  # verdicts never come here
            if len(outputs) == 3:
                outputs_done.set()

    async with (
        ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"])) as fab,
        ZenohFabric(ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as peer,
        open_service(config, load_text(SPEC), fabric=fab) as service,
        anyio.create_task_group() as tg,
    ):
        vsub = peer.subscribe(keys.pattern(SYS, keys.Kind.TRUST, "*/verdict"))
        osub = peer.subscribe(keys.pattern(SYS, keys.Kind.TRUST, "*"))
        tg.start_soon(collect_verdicts, vsub)
        tg.start_soon(collect_outputs, osub)
        await peer.wait_matched(pose)
        await fab.wait_matched(keys.trust(SYS, "ok/verdict"))
        await fab.wait_matched(keys.trust(SYS, "ok"))
        sealer = Sealer("robot")
        for x in (1.0, 2.5, 6.0):
            payload, _ = sealer.seal_message(pose, Pose2D(x=x, y=0.0, theta=0.0))
            await peer.publish(pose, payload)
        with anyio.fail_after(10):
            await done.wait()
            await outputs_done.wait()
        vsub.close()
        osub.close()
        tg.cancel_scope.cancel()
    (k1, src1, v1), (k2, src2, v2) = verdicts
    assert (k1, src1) == (keys.trust(SYS, "ok/verdict"), "tcv")
    assert (k2, src2) == (keys.trust(SYS, "trigger.0/verdict"), "tcv")
    assert summary(v1) == ("ok", 1, False, "output", None, "")
    assert causes(v1) == [(0, "x", 2.5, "x", 1)]
    assert summary(v2) == ("trigger.0", 2, True, "trigger", "critical", "far out")
    assert causes(v2) == [(0, "x", 6.0, "x", 2)]
    assert v1.ts is not None
    assert v1.ts > 0
    assert [(t, o.stream, o.tick, o.value) for t, o in outputs] == [
        (TrustOutput.TYPE, "ok", 0, True),
        (TrustOutput.TYPE, "ok", 1, False),
        (TrustOutput.TYPE, "ok", 2, False),
    ]
    assert service.fabric is not None
    assert service.fabric.stats.verdicts == 2


# -- the command line ---------------------------------------------------------------------------

CLI_SPEC = """\
in latency: Float
in approved: Bool
out ok: Bool
ok = latency < 2.0 && approved
out n: Int
n = 1
trigger !approved "not approved" error
"""
CLI_TRACE = """\
0: latency = 1.0
   approved = true
1: latency = 2.7
2: latency = 1.0
3: approved = false
"""


def run_cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "trust_checker", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )


def test_cli_explain_keeps_stdout_and_writes_json_verdicts_to_stderr(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text(CLI_SPEC)
    (tmp_path / "t.trace").write_text(CLI_TRACE)
    plain = run_cli(tmp_path / "s.dsrv", "--input-file", tmp_path / "t.trace")
    explained = run_cli(tmp_path / "s.dsrv", "--input-file", tmp_path / "t.trace", "--explain")
    assert plain.returncode == explained.returncode == 0, explained.stderr
    expected = run_trace(load_text(CLI_SPEC), read_trace(CLI_TRACE))
    assert plain.stdout.splitlines() == explained.stdout.splitlines() == expected
    assert plain.stderr == ""
    lines = [json.loads(line) for line in explained.stderr.splitlines()]
    assert lines == [
        {
            "stream": "ok",
            "tick": 1,
            "value": False,
            "expr": "latency < 2.0 && approved",
            "because": [
                {"expr": "latency < 2.0", "value": False},
                {"expr": "latency", "value": 2.7, "depth": 1, "input": "latency", "input_tick": 1},
            ],
        },
        {
            "stream": "ok",
            "tick": 3,
            "value": False,
            "expr": "latency < 2.0 && approved",
            "because": [{"expr": "approved", "value": False, "input": "approved", "input_tick": 3}],
        },
        {
            "stream": "trigger.0",
            "tick": 3,
            "value": True,
            "kind": "trigger",
            "expr": "!approved",
            "because": [{"expr": "approved", "value": False, "input": "approved", "input_tick": 3}],
            "message": "not approved",
            "severity": "error",
        },
    ]
