"""ROS 2 over DDS: the types are ROS 2's, byte for byte, and a ROS 2 lidar drives RAP's
lidar-occlusion loop through two dds bridges, its plan coming back as a ROS 2 message.

The independent references: ``rosbags`` (a ROS 2 CDR serializer with ROS 2's message
definitions, nobody's code here) for the bytes, and plain Cyclone DDS participants with
types of their own for the wire (``ros2_lidar_node.py`` in a child process, and a writer
in this process); everything on the loopback interface (``outside_dds.loopback_only``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import anyio
import msgspec
import numpy as np
import pytest
from anyio.streams.buffered import BufferedByteReceiveStream
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from lidar_occlusion.nodes import build
from lidar_occlusion.scans import occluded_scan
from rap_bridges import Bridge, BridgeSpec
from rap_bridges.ros2 import (
    MAPPINGS,
    Frame_,
    FrameHeader_,
    LaserScan_,
    SpinPlan_,
    Twist_,
    Unrepresentable,
    Vector3_,
    dds_topic,
    from_ros,
    ros_name,
    to_ros,
)
from rap_schemas import LaserScan, Odometry, Pose2D, SpinCommand, SpinPlan, Twist, keys
from rap_sdk import MemoryFabric, Sealer
from rap_sdk.testing import Harness, require_binary, stop_process
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from libs.rap_bridges.tests.contract import fast_backoff, until
from libs.rap_bridges.tests.outside_dds import DOMAIN, loopback_only, require_server

STAMP = 1_700_000_000_123_456_789
RAP_MSGS = {
    "rap_msgs/msg/SpinCommand": "float64 omega\nfloat64 duration\n",
    "rap_msgs/msg/SpinPlan": "SpinCommand[] commands\nfloat64 period\n",
    "rap_msgs/msg/FrameHeader": "string key\nstring value\n",
    "rap_msgs/msg/Frame": "FrameHeader[] headers\nuint8[] payload\n",
}
"""RAP's own ROS 2 messages, as docs/bridges/dds.md gives them (.msg files)."""
NODE = Path(__file__).with_name("ros2_lidar_node.py")


@pytest.fixture(scope="module")
def ros2() -> Any:
    """ROS 2 Humble's message definitions and CDR serializer (rosbags), with RAP's own."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in RAP_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


# -- (a) the types ---------------------------------------------------------------------------


def test_the_dds_names_are_ros2s() -> None:
    assert dds_topic("/scan") == "rt/scan"
    assert dds_topic("/tb1/scan") == "rt/tb1/scan"
    names = {t: (m.ros.__idl_typename__, m.ros_name) for t, m in MAPPINGS.items()}
    assert names == {
        "rap.LaserScan/2": ("sensor_msgs::msg::dds_::LaserScan_", "sensor_msgs/msg/LaserScan"),
        "rap.Twist/1": ("geometry_msgs::msg::dds_::Twist_", "geometry_msgs/msg/Twist"),
        "rap.Odometry/1": ("nav_msgs::msg::dds_::Odometry_", "nav_msgs/msg/Odometry"),
        "rap.SpinPlan/1": ("rap_msgs::msg::dds_::SpinPlan_", "rap_msgs/msg/SpinPlan"),
    }
    assert ros_name(Frame_) == "rap_msgs/msg/Frame"


def test_a_scan_is_ros2s_laserscan_byte_for_byte(ros2: Any) -> None:
    scan = occluded_scan(-0.4, 0.8, stamp=STAMP)
    ours = to_ros(scan).serialize()
    theirs = ros2.deserialize_cdr(ours, "sensor_msgs/msg/LaserScan")
    assert (theirs.header.stamp.sec, theirs.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    assert theirs.header.frame_id == "tb1/base_link"
    assert theirs.angle_max == pytest.approx(math.pi - 2 * math.pi / 360, abs=1e-6)
    assert theirs.ranges.tobytes() == scan.ranges  # float32, little-endian: the same bytes
    assert len(theirs.intensities) == 0
    assert ros2.serialize_cdr(theirs, "sensor_msgs/msg/LaserScan") == ours
    back = msgspec.convert(from_ros(LaserScan_.deserialize(ours), LaserScan), LaserScan)
    assert back.stamp == STAMP
    assert back.ranges == scan.ranges
    assert back.angle_min == pytest.approx(scan.angle_min, abs=1e-6)  # via float32


def test_a_clockwise_ros2_scan_with_nan_and_minus_inf_maps_by_the_documented_rules(
    ros2: Any,
) -> None:
    """Written by rosbags as a ROS 2 driver would: a clockwise lidar (negative increment)
    with a NaN (no valid return) and a -inf (too close) beam."""
    msg = ros2.types["sensor_msgs/msg/LaserScan"]
    hdr = ros2.types["std_msgs/msg/Header"]
    time_ = ros2.types["builtin_interfaces/msg/Time"]
    ranges = np.array([1.0, np.nan, 2.0, -np.inf], dtype=np.float32)
    raw = ros2.serialize_cdr(
        msg(
            header=hdr(stamp=time_(sec=10, nanosec=5), frame_id="laser"),
            angle_min=0.3,
            angle_max=0.0,
            angle_increment=-0.1,
            time_increment=0.001,
            scan_time=0.1,
            range_min=0.05,
            range_max=10.0,
            ranges=ranges,
            intensities=np.zeros(4, dtype=np.float32),
        ),
        "sensor_msgs/msg/LaserScan",
    )
    scan = msgspec.convert(from_ros(LaserScan_.deserialize(raw), LaserScan), LaserScan)
    assert list(scan.values()) == [0.0, 2.0, math.inf, 1.0]  # reversed; -inf 0, NaN inf
    assert scan.angle_min == pytest.approx(0.0, abs=1e-6)  # the last beam's angle
    assert scan.angle_increment == pytest.approx(0.1, abs=1e-6)
    assert scan.stamp == 10 * 10**9 + 5 + 3 * 1_000_000  # the first beam is now the last read
    assert scan.frame_id == "laser"


def test_twist_odometry_and_plan_are_ros2s_byte_for_byte(ros2: Any) -> None:
    twist = Twist(linear=0.25, angular=-0.5)
    t = ros2.deserialize_cdr(to_ros(twist).serialize(), "geometry_msgs/msg/Twist")
    assert (t.linear.x, t.linear.y, t.linear.z) == (0.25, 0.0, 0.0)
    assert (t.angular.x, t.angular.y, t.angular.z) == (0.0, 0.0, -0.5)
    odom = Odometry(
        stamp=STAMP, frame_id="odom", pose=Pose2D(x=1.5, y=-2.0, theta=2.0), twist=twist
    )
    ours = to_ros(odom).serialize()
    o = ros2.deserialize_cdr(ours, "nav_msgs/msg/Odometry")
    assert (o.pose.pose.position.x, o.pose.pose.position.y) == (1.5, -2.0)
    q = o.pose.pose.orientation
    assert (q.z, q.w) == pytest.approx((math.sin(1.0), math.cos(1.0)))
    assert ros2.serialize_cdr(o, "nav_msgs/msg/Odometry") == ours
    back = msgspec.convert(from_ros(type(to_ros(odom)).deserialize(ours), Odometry), Odometry)
    assert back.pose.theta == pytest.approx(2.0)
    assert (back.stamp, back.twist) == (STAMP, twist)
    plan = SpinPlan(commands=[SpinCommand(omega=1.0, duration=0.4)], period=8.0)
    ours = to_ros(plan).serialize()
    p = ros2.deserialize_cdr(ours, "rap_msgs/msg/SpinPlan")
    assert [(c.omega, c.duration) for c in p.commands] == [(1.0, 0.4)]
    assert ros2.serialize_cdr(p, "rap_msgs/msg/SpinPlan") == ours
    assert msgspec.convert(from_ros(SpinPlan_.deserialize(ours), SpinPlan), SpinPlan) == plan
    frame = Frame_(headers=[FrameHeader_("rap-type", "test.Reading/1")], payload=b'{"n":1}')
    f = ros2.deserialize_cdr(frame.serialize(), "rap_msgs/msg/Frame")
    assert (f.headers[0].key, f.headers[0].value, f.payload.tobytes()) == (
        "rap-type",
        "test.Reading/1",
        b'{"n":1}',
    )


def _clockwise(*, time_increment: float) -> Any:
    """A ROS 2 scan of a clockwise lidar (negative increment) with this time step."""
    scan = to_ros(occluded_scan(stamp=STAMP))
    return dataclasses.replace(
        scan, angle_increment=-scan.angle_increment, time_increment=time_increment
    )


@pytest.mark.parametrize(
    ("make", "reason"),
    [
        (lambda: to_ros(occluded_scan(stamp=2**31 * 10**9)), "int32 seconds"),
        (
            lambda: to_ros(
                Odometry(
                    stamp=0,
                    frame_id="a\x00b",
                    pose=Pose2D(x=0, y=0, theta=0),
                    twist=Twist(linear=0, angular=0),
                )
            ),
            "NUL",
        ),
        (lambda: from_ros(Twist_(Vector3_(1, 0.5, 0), Vector3_(0, 0, 0)), Twist), "linear.y"),
        (  # a clockwise scan whose beams' times run past an int64 of nanoseconds
            lambda: from_ros(_clockwise(time_increment=1e12), LaserScan),
            "time_increment",
        ),
    ],
)
def test_what_cannot_be_represented_is_refused_with_the_reason(make: Any, reason: str) -> None:
    with pytest.raises(Unrepresentable, match=reason):
        make()


def test_a_dds_spec_takes_ros2_topic_names_and_cdr_only_for_dds() -> None:
    ok = BridgeSpec(protocol="dds", url="dds://0", address="/tb1/scan", format="json")
    assert (ok.domain, ok.where) == (0, "dds://0/tb1/scan")
    for address in ("scan", "/1scan", "/a//b", "/scan/", "/sc-an"):
        with pytest.raises(ValueError, match="not a ROS 2 topic name"):
            BridgeSpec(protocol="dds", url="dds://0", address=address)
    with pytest.raises(ValueError, match=r"cdr \(ROS 2 messages\) applies to dds only"):
        BridgeSpec(protocol="mqtt", url="mqtt://x:1", address="a", format="cdr")
    from libs.rap_bridges.tests.contract import Reading

    with pytest.raises(ValueError, match="has no ROS 2 message"):
        Bridge(
            "x",
            spec("/scan"),
            MemoryFabric(),
            keys.data("lo", "r"),
            direction="in",
            message=Reading,
        )


# -- (b) on the wire ---------------------------------------------------------------------------


@pytest.fixture
def domain() -> int:
    require_server()
    loopback_only()
    return DOMAIN


def spec(address: str, **kw: Any) -> BridgeSpec:
    return BridgeSpec(protocol="dds", url=f"dds://{DOMAIN}", address=address, format="cdr", **kw)


@pytest.mark.anyio
async def test_a_ros2_twist_rap_cannot_hold_is_rejected_counted_and_the_bridge_goes_on(
    domain: int,
) -> None:
    topic = f"/twist_{os.getpid()}/cmd_vel"
    async with Harness(system="lo") as h, anyio.create_task_group() as tg:
        b = Bridge(
            "ros-twist",
            spec(topic, qos=1),
            h.fabric,
            keys.data("lo", "tb1/cmd_vel"),
            direction="in",
            message=Twist,
            backoff=fast_backoff(),
        )
        await tg.start(b.run)
        dp = DomainParticipant(domain)
        try:
            qos = Qos(
                Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1)),
                Policy.Durability.TransientLocal,
                Policy.History.KeepLast(10),
            )
            w = DataWriter(dp, Topic(dp, dds_topic(topic), Twist_), qos)
            with anyio.fail_after(10):
                await b.wait_connected()
            for lin in (0.5, 0.75):  # the middle one moves sideways: RAP's twist cannot
                w.write(Twist_(Vector3_(lin, 0.0, 0.0), Vector3_(0.0, 0.0, 0.1)))
                if lin == 0.5:
                    w.write(Twist_(Vector3_(0.1, 0.3, 0.0), Vector3_(0.0, 0.0, 0.0)))
            await h.wait_for(lambda r: len(h.of(keys.Kind.DATA, "tb1/cmd_vel")) == 2)
        finally:
            dp.__del__()
        tg.cancel_scope.cancel()
    got = [r.decode(Twist) for r in h.of(keys.Kind.DATA, "tb1/cmd_vel")]
    assert got == [Twist(linear=0.5, angular=0.1), Twist(linear=0.75, angular=0.1)]
    assert b.stats.rejected == 1
    reasons = " | ".join(b.stats.rejections.by_reason)  # numbers are folded into N
    assert "Twist does not map to rap.Twist/N: linear.y is N.N: RAP's twist is planar" in reasons


@pytest.mark.anyio
async def test_cyclone_ddss_own_tool_reads_the_plan_an_out_bridge_writes(domain: int) -> None:
    """``cyclonedds subscribe`` (Cyclone DDS's command-line tool) finds the topic and its
    type over DDS itself and prints the plan the bridge wrote."""
    tool = require_binary("cyclonedds", hint="it comes with the cyclonedds Python package")
    topic = f"/tool_{os.getpid()}/spin_config"
    key = keys.data("lo", "tb1/spin_config")
    plan = SpinPlan(commands=[SpinCommand(omega=1.0, duration=0.4)], period=8.0)
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        b = Bridge(
            "plan-out",
            spec(topic, qos=1),
            fabric,
            key,
            direction="out",
            message=SpinPlan,
            backoff=fast_backoff(),
        )
        await tg.start(b.run)
        await fabric.publish(key, Sealer("executor").seal_out(key, plan))  # buffered: no reader
        run = [tool, "subscribe", dds_topic(topic), "-i", str(domain), "-r", "2s"]
        proc = await anyio.open_process(
            [*run, "--suppress-progress-bar"], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE
        )
        out = b""
        try:  # it subscribes until interrupted: read until the plan is there
            assert proc.stdout is not None
            with anyio.fail_after(30):
                while b"SpinPlan_(" not in out:
                    out += await proc.stdout.receive()
                while b")\n" not in out[out.index(b"SpinPlan_(") :]:
                    out += await proc.stdout.receive()
        finally:
            await stop_process(proc, grace=5)
            await proc.aclose()
        tg.cancel_scope.cancel()
    expected = b"SpinPlan_(commands=[SpinCommand_(omega=1.0, duration=0.4)], period=8.0)"
    assert expected in out, out
    assert b.stats.sent == 1


@pytest.mark.anyio
async def test_a_publisher_whose_qos_cannot_match_is_reported_with_the_fix(
    domain: int, caplog: pytest.LogCaptureFixture
) -> None:
    """A default ROS 2 publisher (reliable, volatile) and an in bridge at qos 1, which
    asks for transient-local: no match, said with what to do, again at each attempt."""
    topic = f"/volatile_{os.getpid()}/cmd_vel"
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        b = Bridge(
            "ros-twist",
            spec(topic, qos=1),
            fabric,
            keys.data("lo", "tb1/cmd_vel"),
            direction="in",
            message=Twist,
            backoff=fast_backoff(),
        )
        await tg.start(b.run)
        dp = DomainParticipant(domain)
        try:
            qos = Qos(Policy.Reliability.Reliable(max_blocking_time=0), Policy.Durability.Volatile)
            w = DataWriter(dp, Topic(dp, dds_topic(topic), Twist_), qos)
            await until(lambda: b.stats.connect_failures >= 2)
        finally:
            dp.__del__()
        tg.cancel_scope.cancel()
    del w
    assert not b.stats.connects
    said = caplog.text
    assert "does not offer the durability this reader asks for" in said
    assert "or give the bridge qos: 0" in said


async def _lines(proc: Any) -> AsyncIterator[dict[str, Any]]:
    lines = BufferedByteReceiveStream(proc.stdout)
    while True:
        try:
            yield json.loads(await lines.receive_until(b"\n", 1 << 20))
        except (anyio.EndOfStream, anyio.IncompleteRead):
            return


@pytest.mark.anyio
async def test_a_ros2_lidar_drives_the_occlusion_loop_and_gets_its_plan_as_ros2(
    domain: int,
) -> None:
    """The lidar node publishes sensor_msgs/LaserScan on rt/<ns>/scan (best effort, as
    ROS 2 lidar drivers do; the bridge takes it at qos 0); the five MAPLE-K stages find the
    occluded sector and plan a spin; the executor's plan leaves through an out bridge
    (qos 1: reliable, transient-local) and the node gets it as rap_msgs/SpinPlan."""
    ns = f"/ros2_{os.getpid()}/tb1"
    loop = build("tb1")
    async with Harness(system="lo") as h:
        await h.hold(open_service(KnowledgeConfig(system="lo"), fabric=h.fabric))
        await h.start(*loop.nodes)
        scans = Bridge(
            "ros-scan",
            spec(f"{ns}/scan", qos=0),
            h.fabric,
            keys.data("lo", "tb1/scan"),
            direction="in",
            message=LaserScan,
            backoff=fast_backoff(),
        )
        plans = Bridge(
            "ros-plan",
            spec(f"{ns}/spin_config", qos=1),
            h.fabric,
            keys.data("lo", "tb1/spin_config"),
            direction="out",
            message=SpinPlan,
            backoff=fast_backoff(),
        )
        async with anyio.create_task_group() as tg:
            await tg.start(scans.run)
            await tg.start(plans.run)
            args = [sys.executable, str(NODE), "--domain", str(domain), "--ns", ns]
            proc = await anyio.open_process(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
            try:
                with anyio.fail_after(30):
                    async for event in _lines(proc):
                        if "plan" in event:
                            break
                    else:
                        raise AssertionError("the lidar node stopped without a plan")
            finally:
                assert proc.stdin is not None
                await proc.stdin.aclose()
                with anyio.move_on_after(10):
                    await proc.wait()
                await stop_process(proc, grace=5)
                await proc.aclose()
            tg.cancel_scope.cancel()
    ros_plan = SpinPlan(
        commands=[SpinCommand(**c) for c in event["plan"]["commands"]],
        period=event["plan"]["period"],
    )
    rap_plan = h.of(keys.Kind.DATA, "tb1/spin_config")[0].decode(SpinPlan)
    assert ros_plan == rap_plan  # field for field
    # both ends of the +-0.4 rad sector and back: three commands, net zero
    assert len(ros_plan.commands) == 3
    assert sum(c.omega * c.duration for c in ros_plan.commands) == pytest.approx(0, abs=1e-9)
    first = h.of(keys.Kind.DATA, "tb1/scan")[0]
    assert first.envelope is not None
    assert first.envelope.source == "ros-scan"
    scan = first.decode(LaserScan)
    assert scan.frame_id == f"{ns[1:]}/base_link"
    assert scan.beams == 360
    assert math.isinf(max(scan.values()))
    assert scan.stamp > 1_700_000_000 * 10**9  # the node's wall-clock stamp, in ns
    assert scans.stats.rejected == 0
    assert plans.stats.sent >= 1
