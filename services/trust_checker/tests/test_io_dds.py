"""The checker's inputs from ROS 2 topics over DDS. The ROS 2 side is a plain Cyclone DDS
participant with message types of its own (written from ROS 2's definitions), with ROS
2's default publisher QoS (reliable, volatile); all on the loopback interface, in a
domain of this test process's own (``outside_dds.loopback_only``)."""

# No "from __future__ import annotations": cyclonedds reads the IDL fields' annotations.
import math
import os
import signal
import subprocess
import sys
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import anyio
import pytest
from anyio.streams.text import TextReceiveStream
from cyclonedds.core import DDSStatus, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float64, sequence, uint8
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from trust_checker.config import DdsConfig, DdsTopic, ServiceConfig
from trust_checker.io.session import SwapRequest
from trust_checker.io.specs import load_text
from trust_checker.service import TrustService, open_service

from libs.rap_bridges.tests.outside_dds import DOMAIN, loopback_only, require_server
from services.trust_checker.tests.io_support import (
    FakeRunner,
    FakeSpec,
    RecordingSink,
    fake_loader,
)

pytestmark = [pytest.mark.anyio]

NS = f"/tc_{os.getpid()}"


@dataclass
class Float64_(IdlStruct, typename="std_msgs::msg::dds_::Float64_"):
    data: float64


@dataclass
class FrameHeader_(IdlStruct, typename="rap_msgs::msg::dds_::FrameHeader_"):
    key: str
    value: str


@dataclass
class Frame_(IdlStruct, typename="rap_msgs::msg::dds_::Frame_"):
    headers: Annotated[Sequence[FrameHeader_], sequence(FrameHeader_)]
    payload: Annotated[Sequence[int], sequence(uint8)]


ROS2_DEFAULT = Qos(
    Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1)),
    Policy.Durability.Volatile,
    Policy.History.KeepLast(10),
)


@pytest.fixture(autouse=True)
def _dds() -> None:
    require_server()
    loopback_only()


class Ros2Node:
    """A ROS 2 node's publishers, as plain Cyclone DDS (in this process)."""

    def __init__(self) -> None:
        self.participant = DomainParticipant(DOMAIN)

    def publisher(self, topic: str, kind: type[IdlStruct]) -> DataWriter[Any]:
        dp = self.participant
        return DataWriter(dp, Topic(dp, f"rt{topic}", kind), ROS2_DEFAULT)

    def close(self) -> None:
        self.participant.__del__()


async def matched(writer: DataWriter[Any]) -> None:
    """Until the checker's reader is there (a volatile writer keeps nothing for it)."""
    writer.set_status_mask(DDSStatus.PublicationMatched)
    ws = WaitSet(writer.participant)
    ws.attach(writer)
    with anyio.fail_after(10):
        while not writer.get_publication_matched_status().current_count:
            await anyio.to_thread.run_sync(ws.wait, duration(seconds=0.1))


@asynccontextmanager
async def checker(
    spec: Any, topics: dict[str, DdsTopic], **kw: Any
) -> AsyncIterator[tuple[TrustService, RecordingSink, Ros2Node]]:
    sink = RecordingSink()
    config = ServiceConfig(dds=DdsConfig(domain=DOMAIN, topics=topics))
    node = Ros2Node()
    try:
        async with open_service(config, spec, sinks=[sink], **kw) as service:
            yield service, sink, node
    finally:
        node.close()


def frame(payload: bytes) -> Frame_:
    return Frame_(headers=[], payload=payload)


async def test_ros2_float64s_give_outputs_and_a_nan_is_refused() -> None:
    spec = load_text("in latency: Float\nout ok: Bool\nok = latency < 2.0\n", "lat.dsrv")
    topics = {"latency": DdsTopic(f"{NS}/latency", "std_msgs/msg/Float64")}
    async with checker(spec, topics) as (service, sink, node):
        w = node.publisher(f"{NS}/latency", Float64_)
        await matched(w)
        for v in (1.5, math.nan, 2.5):
            w.write(Float64_(v))
        await sink.wait_for(n_outs=2)
        assert service.dds is not None
        assert service.dds.stats.rejections.total == 1
        assert "not a finite number" in " ".join(service.dds.stats.rejections.by_reason)
    assert [(o.stream, o.value) for o in sink.outs] == [("ok", True), ("ok", False)]


async def test_frames_in_the_codecs_forms_and_the_readers_follow_a_hot_swap() -> None:
    runner = FakeRunner(FakeSpec(("a",), ("s",)))
    topics = {"a": DdsTopic(f"{NS}/a"), "b": DdsTopic(f"{NS}/b")}
    async with checker(runner, topics, loader=fake_loader) as (service, sink, node):
        a = node.publisher(f"{NS}/a", Frame_)
        await matched(a)
        for payload in (b"1", b'{"Int": 2}', b'{"value": 3}', b"not json"):
            a.write(frame(payload))
        await sink.wait_for(n_outs=3)
        assert service.dds is not None
        assert service.dds.stats.rejections.total == 1
        swap = SwapRequest("in b\nout s\n", "<test>", "test")
        await service.session.submit(swap)
        with anyio.fail_after(5):
            await swap.done.wait()
        assert swap.result is not None
        assert swap.result.ok
        b = node.publisher(f"{NS}/b", Frame_)
        await matched(b)  # the checker made a reader for the new spec's input
        b.write(frame(b"4"))
        await sink.wait_for(n_outs=4)
        assert service.dds.stats.readers == 1  # the reader of a is gone
    assert [o.value for o in sink.outs] == [1, 3, 6, 10]  # the history carried over


async def test_the_command_line_reads_a_ros2_topic(tmp_path: Path) -> None:
    spec = tmp_path / "lat.dsrv"
    spec.write_text("in latency: Float\nout ok: Bool\nok = latency < 2.0\n")
    topics = '{"latency": {"topic": "' + NS + '/cli", "type": "std_msgs/msg/Float64"}}'
    args = [sys.executable, "-m", "trust_checker", str(spec), "--dds", str(DOMAIN)]
    node = Ros2Node()
    try:
        async with await anyio.open_process(
            [*args, "--dds-topics", topics, "--log-level", "WARNING"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        ) as proc:
            assert proc.stdout is not None
            w = node.publisher(f"{NS}/cli", Float64_)
            await matched(w)
            w.write(Float64_(3.0))
            out = ""
            with anyio.fail_after(20):
                async for text in TextReceiveStream(proc.stdout):
                    out += text
                    if "\n" in out:
                        break
            proc.send_signal(signal.SIGINT)
            with anyio.fail_after(10):
                assert await proc.wait() == 0
    finally:
        node.close()
    assert out.startswith("ok[0] = "), out
    assert "false" in out.lower()


def test_dds_options_need_dds() -> None:
    res = subprocess.run(
        [sys.executable, "-m", "trust_checker", "x.dsrv", "--dds-qos", "1"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert res.returncode == 2
    assert "the --dds-* options go with --dds DOMAIN" in res.stderr
