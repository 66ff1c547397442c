"""Messages of the lidar-occlusion case (docs/lidar_occlusion.md).

Angles are radians in the robot's base frame (x forward, counter-clockwise positive);
the lidar mount offset, if any, is applied by the publisher and named in ``frame_id``.
"""

from __future__ import annotations

import math
from typing import Annotated

import msgspec

from .message import Message

__all__ = [
    "LaserScan",
    "LidarMask",
    "Odometry",
    "Pose2D",
    "SimTime",
    "SpinCommand",
    "SpinPlan",
    "Twist",
]

# Bounds that also make a number finite: msgspec refuses NaN and values past them.
Angle = Annotated[float, msgspec.Meta(ge=-4 * math.pi, le=4 * math.pi, description="radians")]
Increment = Annotated[float, msgspec.Meta(gt=0, le=2 * math.pi, description="radians")]
Metres = Annotated[float, msgspec.Meta(ge=0, le=1e6, description="metres")]
Coordinate = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9, description="metres")]
Speed = Annotated[float, msgspec.Meta(ge=-1e3, le=1e3)]
Seconds = Annotated[float, msgspec.Meta(ge=0, le=86_400, description="seconds")]
Nanos = Annotated[int, msgspec.Meta(ge=0, description="integer nanoseconds")]
Range = Annotated[float, msgspec.Meta(ge=0, description="metres; inf: no return")]
Beams = 100_000
"""The most beams a scan or mask may have."""


class LaserScan(Message, frozen=True):
    TYPE = "rap.LaserScan/1"

    stamp: Nanos
    """Sensor time of the first beam."""
    frame_id: str
    angle_min: Angle
    angle_increment: Increment
    range_min: Metres
    range_max: Metres
    ranges: Annotated[list[Range], msgspec.Meta(max_length=Beams)]
    """Metres; ``inf`` where a beam has no return (occluded or beyond range); never
    NaN nor negative."""
    scan_time: Seconds = 0.2

    def __post_init__(self) -> None:
        if self.range_min > self.range_max:
            raise ValueError(
                f"range_min {self.range_min} is above range_max {self.range_max}; a scan's "
                "valid ranges are range_min..range_max"
            )


class Pose2D(Message, frozen=True):
    TYPE = "rap.Pose2D/1"

    x: Coordinate
    y: Coordinate
    theta: Angle


class Twist(Message, frozen=True):
    """Planar velocity command: forward m/s and yaw rate rad/s."""

    TYPE = "rap.Twist/1"

    linear: Speed
    """m/s."""
    angular: Speed
    """rad/s."""


class Odometry(Message, frozen=True):
    TYPE = "rap.Odometry/1"

    stamp: Nanos
    frame_id: str
    pose: Pose2D
    twist: Twist


class SimTime(Message, frozen=True):
    """The simulator's clock (``rap/<system>/data/clock``): sim time, ns."""

    TYPE = "rap.SimTime/1"

    t: Nanos
    realtime_factor: Annotated[float, msgspec.Meta(ge=0, le=1e6)] = 0.0
    """0 in lockstep (as fast as possible), else sim seconds per wall second."""


class SpinCommand(Message, frozen=True):
    """Turn in place at ``omega`` rad/s for ``duration`` s."""

    TYPE = "rap.SpinCommand/1"

    omega: Speed
    """rad/s (the Legitimate stage decides what is safe; this only keeps it finite)."""
    duration: Seconds


class SpinPlan(Message, frozen=True):
    """Every ``period`` s the robot runs ``commands`` in order, then resumes nominal
    navigation; an empty plan restores nominal behaviour."""

    TYPE = "rap.SpinPlan/1"

    commands: Annotated[list[SpinCommand], msgspec.Meta(max_length=1000)]
    period: Annotated[float, msgspec.Meta(gt=0, le=86_400)] = 8.0


class LidarMask(Message, frozen=True):
    """``occluded[i]`` is True where beam i is judged occluded."""

    TYPE = "rap.LidarMask/1"

    angle_min: Angle
    angle_increment: Increment
    occluded: Annotated[list[bool], msgspec.Meta(max_length=Beams)]
    frame_id: str = "base_link"
