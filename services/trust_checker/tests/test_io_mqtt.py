"""The checker on MQTT, end to end through a mosquitto the test starts on a free port."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiomqtt
import anyio
import pytest
from trust_checker.config import MqttConfig, ServiceConfig, TopicMap
from trust_checker.io.mqtt import MqttTransport
from trust_checker.io.session import Session
from trust_checker.service import open_service

from services.trust_checker.tests.io_support import (
    FakeRunner,
    FakeSpec,
    Mosquitto,
    fake_loader,
    mosquitto,
)

pytestmark = [pytest.mark.anyio]


@dataclass
class Peer:
    """The other side: publishes inputs, collects what the checker publishes."""

    client: aiomqtt.Client
    got: list[tuple[str, Any]] = field(default_factory=list)
    changed: anyio.Event = field(default_factory=anyio.Event)

    async def collect(self) -> None:
        async for message in self.client.messages:
            self.got.append((message.topic.value, json.loads(bytes(message.payload))))
            self.changed.set()

    async def send(self, topic: str, payload: str | bytes) -> None:
        await self.client.publish(topic, payload)

    async def wait(self, n: int, timeout: float = 5.0) -> list[tuple[str, Any]]:
        with anyio.fail_after(timeout):
            while len(self.got) < n:
                self.changed = anyio.Event()
                await self.changed.wait()
        return self.got

    def on(self, topic: str) -> list[Any]:
        return [p for t, p in self.got if t == topic]


@asynccontextmanager
async def checker(
    tmp_path: Path,
    runner: Any,
    *,
    config: dict[str, Any] | None = None,
    tick: str = "message",
    loader: Any = fake_loader,
    listen: tuple[str, ...] = ("#",),
) -> AsyncIterator[tuple[Session, MqttTransport, Peer]]:
    async with mosquitto(tmp_path) as broker:
        cfg = MqttConfig(port=broker.port, timeout=5.0, **(config or {}))
        async with (
            open_service(ServiceConfig(tick=tick, mqtt=cfg), runner, loader=loader) as service,
            aiomqtt.Client("127.0.0.1", broker.port, timeout=5.0) as client,
            anyio.create_task_group() as tg,
        ):
            assert service.mqtt is not None
            peer = Peer(client)
            for topic in listen:
                await client.subscribe(topic)
            tg.start_soon(peer.collect)
            try:
                yield service.session, service.mqtt, peer
            finally:
                tg.cancel_scope.cancel()


async def test_inputs_in_all_three_forms_and_plain_outputs(tmp_path: Path) -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    async with checker(tmp_path, mon, listen=("s",)) as (_session, transport, peer):
        await peer.send("a", "1")
        await peer.send("a", '{"Int": 2}')
        await peer.send("a", '{"value": 3}')
        await peer.send("a", '"bottom"')
        await peer.wait(4)
    assert peer.on("s") == [
        {"value": 1},
        {"value": 3},
        {"value": 6},
        {"value": None, "deferred": True},
    ]
    assert transport.stats.published == 4


async def test_tagged_outputs_and_bad_payloads_are_rejected(tmp_path: Path) -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    cfg = {"tagged": True}
    async with checker(tmp_path, mon, config=cfg, listen=("s",)) as (_s, transport, peer):
        await peer.send("a", "{nope")
        await peer.send("a", '{"Int": "seven"}')
        await peer.send("a", "")
        await peer.send("a", "7")
        await peer.send("a", '"bottom"')
        await peer.wait(2)
    assert peer.on("s") == [{"Int": 7}, "Unknown"]
    rejections = transport.stats.rejections
    assert rejections.total == 3
    assert sorted(rejections.by_reason) == [
        'empty payload - send one JSON value: N, {"Int": N} or {"value": N}',
        "payload: undecodable: JSON is malformed: object keys must be strings",
        "tagged value rejected: not a tagged value: {'Int': 'seven'} - write e.g. "
        '{"Int": N}, {"Str": "a"}, "Unit" or "Unknown"',
    ]


async def test_topic_map_for_inputs_and_outputs(tmp_path: Path) -> None:
    mon = FakeRunner(FakeSpec(("a", "b"), ("s",)))
    cfg = {
        "topics": {
            "a": TopicMap("robot/+/speed"),
            "b": TopicMap("robot/b"),
            "s": TopicMap("verdicts/s"),
        }
    }
    async with checker(tmp_path, mon, config=cfg, listen=("verdicts/#", "s")) as (_s, _t, peer):
        await peer.send("a", "100")  # not a's topic any more
        await peer.send("robot/1/speed", "1")
        await peer.send("robot/b", '{"value": 2}')
        await peer.wait(2)
    assert peer.got == [("verdicts/s", {"value": 1}), ("verdicts/s", {"value": 3})]


async def test_hot_swap_carries_history_and_follows_the_new_inputs(tmp_path: Path) -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    listen = ("s", "t", "trust/status")
    async with checker(tmp_path, mon, listen=listen) as (session, _t, peer):
        await peer.send("a", "5")
        await peer.wait(1)
        await peer.send("trust/spec", json.dumps({"spec": "in c\nout t\n"}))
        await peer.wait(2)
        await peer.send("a", "1000")  # no longer an input: not a tick
        await peer.send("c", "2")
        await peer.wait(3)
    assert peer.on("s") == [{"value": 5}]
    assert peer.on("t") == [{"value": 7}]  # the total carried over
    (status,) = peer.on("trust/status")
    assert status["ok"] is True
    assert status["inputs"] == ["c"]
    assert session.stats.swaps == 1


async def test_bad_swap_is_refused_and_the_old_spec_keeps_running(tmp_path: Path) -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))
    listen = ("s", "trust/status")
    async with checker(tmp_path, mon, listen=listen) as (session, _t, peer):
        await peer.send("trust/spec", json.dumps({"spec": "in a\ngarbage\n", "path": "n.dsrv"}))
        await peer.wait(1)
        await peer.send("trust/spec", "not json")
        await peer.wait(2)
        await peer.send("a", "4")
        await peer.wait(3)
    first, second = peer.on("trust/status")
    assert first["ok"] is False
    assert first["problems"][0].startswith("n.dsrv:2:1: unexpected 'garbage'")
    assert second["ok"] is False
    assert "refused" in second["problems"][0]
    assert peer.on("s") == [{"value": 4}]
    assert session.stats.swaps_rejected == 1


async def test_window_policy_over_mqtt(tmp_path: Path) -> None:
    mon = FakeRunner(FakeSpec(("a", "b"), ("s",)))
    async with checker(tmp_path, mon, tick="window:300ms", listen=("s",)) as (_s, _t, peer):
        await peer.send("a", "1")
        await peer.send("b", "2")
        await peer.send("a", "3")
        await peer.wait(1)
    assert peer.on("s") == [{"value": 5}]
    assert mon.steps[0][0] == {"a": 3, "b": 2}


# -- with the real monitor and parser ----------------------------------------------------


async def test_real_monitor_hot_swap_keeps_history_and_refuses_a_bad_spec(
    tmp_path: Path,
) -> None:
    from trust_checker.io.specs import load_text

    first = "in x: Int\nout prev: Int\nprev = x[-1, 0]\n"
    second = "in x: Int\nout sum: Int\nsum = x + default(x[1], 0)\n"
    listen = ("prev", "sum", "trust/status")
    spec = load_text(first)  # open_service runs it with a SpecRunner
    async with checker(tmp_path, spec, loader=load_text, listen=listen) as (session, _t, peer):
        await peer.send("x", "1")
        await peer.send("x", '{"Int": 2}')
        await peer.wait(2)
        await peer.send("trust/spec", json.dumps({"spec": "in x: Int\nout y\ny = x +\n"}))
        await peer.wait(3)
        await peer.send("x", '{"value": 3}')  # the old spec still runs: prev = 2
        await peer.wait(4)
        await peer.send("trust/spec", json.dumps({"spec": second, "path": "second.dsrv"}))
        await peer.wait(5)
        await peer.send("x", "5")  # x[1] is 3, from before the swap
        await peer.send("x", '"Unknown"')  # ⊥ in, ⊥ out
        await peer.send("x", '{"Str": "no"}')  # refused: x is an Int
        await peer.send("x", "6")  # its output shows the refusal was handled first
        await peer.wait(8)
    assert peer.on("prev") == [{"value": 0}, {"value": 1}, {"value": 2}]
    # the refused input took no tick: x[1] is the ⊥ before it, defaulted to 0
    assert peer.on("sum") == [{"value": 8}, {"value": None, "deferred": True}, {"value": 6}]
    bad, good = peer.on("trust/status")
    assert bad["ok"] is False
    assert bad["problems"][0].startswith("<mqtt:trust/spec>:3:")
    assert good["ok"] is True
    assert good["outputs"] == ["sum"]
    assert session.stats.input_errors == 1


async def test_reconnects_after_the_broker_restarts_and_keeps_history(tmp_path: Path) -> None:
    mon = FakeRunner(FakeSpec(("a",), ("s",)))

    async def exchange(port: int, value: str) -> Any:
        async with aiomqtt.Client("127.0.0.1", port, timeout=5.0) as client:
            await client.subscribe("s")
            await client.publish("a", value)
            with anyio.fail_after(5):
                async for message in client.messages:
                    return json.loads(bytes(message.payload))
        raise AssertionError("no output")

    first = Mosquitto(tmp_path)
    port = first.port
    config = ServiceConfig(mqtt=MqttConfig(port=port, timeout=5.0))
    async with anyio.create_task_group() as tg:
        await tg.start(first.run)
        async with open_service(config, mon, loader=fake_loader) as service:
            transport = service.mqtt
            assert transport is not None
            assert await exchange(port, "5") == {"value": 5}
            await first.stop()
            async with mosquitto(tmp_path, port):
                with anyio.fail_after(10):
                    while transport.stats.connects < 2:
                        await transport.connected.wait()
                assert await exchange(port, "2") == {"value": 7}  # the history lived on
