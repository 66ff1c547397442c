"""A ROS 2 robot as DDS sees it, written with plain Cyclone DDS: a lidar publishing
``sensor_msgs/msg/LaserScan`` on ``<ns>/scan`` and a node subscribing to
``rap_msgs/msg/SpinPlan`` on ``<ns>/spin_config`` (run by ``test_dds_ros2.py``;
``python ros2_lidar_node.py --help``).

Its types are its own, written from ROS 2's message definitions (not the bridge's code),
under ROS 2's DDS names; its QoS is ROS 2's: the scans with the sensor-data profile (best
effort, volatile, depth 5), the plan as latched configuration (reliable, transient-local,
depth 1). It publishes a 360-beam scan every 0.1 s (a ring of walls at 3 m, nothing
returning in ``[--from, --from + --width)`` rad: something covers that part of the
lidar) once the bridge's reader matched, prints each plan it gets as a JSON line
``{"plan": {...}, "scans": <published so far>}`` and stops after ``--max-scans`` scans
or at the end of its input.
"""

import argparse
import json
import math
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated

from cyclonedds.core import (
    DDSStatus,
    InstanceState,
    ReadCondition,
    SampleState,
    ViewState,
    WaitSet,
)
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float32, float64, int32, sequence, uint32
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32


@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time_
    frame_id: str


@dataclass
class LaserScan_(IdlStruct, typename="sensor_msgs::msg::dds_::LaserScan_"):
    header: Header_
    angle_min: float32
    angle_max: float32
    angle_increment: float32
    time_increment: float32
    scan_time: float32
    range_min: float32
    range_max: float32
    ranges: Annotated[Sequence[float], sequence(float32)]
    intensities: Annotated[Sequence[float], sequence(float32)]


@dataclass
class SpinCommand_(IdlStruct, typename="rap_msgs::msg::dds_::SpinCommand_"):
    omega: float64
    duration: float64


@dataclass
class SpinPlan_(IdlStruct, typename="rap_msgs::msg::dds_::SpinPlan_"):
    commands: Annotated[Sequence[SpinCommand_], sequence(SpinCommand_)]
    period: float64


BEAMS = 360
SENSOR_DATA = Qos(
    Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5)
)
LATCHED = Qos(
    Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1)),
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(1),
)


def scan(stamp_ns: int, start: float, width: float, frame_id: str) -> LaserScan_:
    inc = 2 * math.pi / BEAMS
    ranges = []
    for i in range(BEAMS):
        angle = -math.pi + i * inc
        ranges.append(math.inf if (angle - start) % (2 * math.pi) < width else 3.0)
    return LaserScan_(
        header=Header_(Time_(stamp_ns // 10**9, stamp_ns % 10**9), frame_id),
        angle_min=-math.pi,
        angle_max=-math.pi + (BEAMS - 1) * inc,
        angle_increment=inc,
        time_increment=0.1 / BEAMS,
        scan_time=0.1,
        range_min=0.1,
        range_max=12.0,
        ranges=ranges,
        intensities=[100.0] * BEAMS,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--domain", type=int, required=True)
    ap.add_argument("--ns", required=True, help="the robot's namespace, e.g. /tb1")
    ap.add_argument("--from", dest="start", type=float, default=-0.4)
    ap.add_argument("--width", type=float, default=0.8)
    ap.add_argument("--max-scans", type=int, default=200)
    args = ap.parse_args()
    dp = DomainParticipant(args.domain)
    writer = DataWriter(dp, Topic(dp, f"rt{args.ns}/scan", LaserScan_), SENSOR_DATA)
    reader = DataReader(dp, Topic(dp, f"rt{args.ns}/spin_config", SpinPlan_), LATCHED)
    done = threading.Event()
    published = [0]

    def plans() -> None:
        waitset = WaitSet(dp)
        waitset.attach(ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any))
        while not done.is_set():
            waitset.wait(duration(seconds=0.1))
            for p in reader.take(10):
                if p.sample_info.valid_data:
                    commands = [{"omega": c.omega, "duration": c.duration} for c in p.commands]
                    plan = {"commands": commands, "period": p.period}
                    sys.stdout.write(json.dumps({"plan": plan, "scans": published[0]}) + "\n")
                    sys.stdout.flush()

    def end_of_input() -> None:
        sys.stdin.read()
        done.set()

    threading.Thread(target=plans, daemon=True).start()
    threading.Thread(target=end_of_input, daemon=True).start()
    writer.set_status_mask(DDSStatus.PublicationMatched)
    matched = WaitSet(dp)
    matched.attach(writer)
    while not done.is_set() and not writer.get_publication_matched_status().current_count:
        matched.wait(duration(seconds=0.1))  # a best-effort scan before that is lost
    sys.stdout.write(json.dumps({"matched": True}) + "\n")
    sys.stdout.flush()
    while not done.is_set() and published[0] < args.max_scans:
        writer.write(scan(time.time_ns(), args.start, args.width, f"{args.ns[1:]}/base_link"))
        published[0] += 1
        done.wait(0.1)  # the lidar's period
    done.wait()
    dp.__del__()


if __name__ == "__main__":
    main()
