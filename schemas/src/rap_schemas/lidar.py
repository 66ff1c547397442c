"""Messages of the lidar-occlusion case (docs/lidar_occlusion.md).

Angles are radians in the robot's base frame (x forward, counter-clockwise positive);
the lidar mount offset, if any, is applied by the publisher and named in ``frame_id``.
"""

from __future__ import annotations

import math
import sys
from array import array
from collections.abc import Iterable
from typing import Annotated, Any, cast

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
    "pack_flags",
    "pack_ranges",
]

# Bounds that also make a number finite: msgspec refuses NaN and values past them.
Angle = Annotated[float, msgspec.Meta(ge=-4 * math.pi, le=4 * math.pi, description="radians")]
Increment = Annotated[float, msgspec.Meta(gt=0, le=2 * math.pi, description="radians")]
Metres = Annotated[float, msgspec.Meta(ge=0, le=1e6, description="metres")]
Coordinate = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9, description="metres")]
Speed = Annotated[float, msgspec.Meta(ge=-1e3, le=1e3)]
Seconds = Annotated[float, msgspec.Meta(ge=0, le=86_400, description="seconds")]
Nanos = Annotated[int, msgspec.Meta(ge=0, description="integer nanoseconds")]
Beams = 100_000
"""The most beams a scan or mask may have."""

PackedRanges = Annotated[
    bytes,
    msgspec.Meta(
        max_length=4 * Beams,
        description="packed float32, little-endian, 4 bytes per beam: metres >= 0, "
        "inf where a beam has no return; never NaN nor negative",
        extra_json_schema={"contentMediaType": "application/x.rap.float32le"},
    ),
]
PackedFlags = Annotated[
    bytes,
    msgspec.Meta(
        max_length=Beams,
        description="packed flags, 1 byte per beam: 0 (false) or 1 (true)",
        extra_json_schema={"contentMediaType": "application/x.rap.bool8"},
    ),
]

_LITTLE = sys.byteorder == "little"


def pack_ranges(values: Iterable[float] | Any) -> bytes:
    """Ranges (a list of floats or a numpy array) packed for :class:`LaserScan`:
    float32, little-endian. Values are rounded to float32 once, here, so a co-located
    reader and a remote one see the same numbers."""
    if hasattr(values, "astype"):  # a numpy array: one C conversion
        return bytes(values.astype("<f4").tobytes())
    packed = array("f", values)
    if not _LITTLE:
        packed.byteswap()
    return packed.tobytes()


def pack_flags(values: Iterable[bool] | Any) -> bytes:
    """Flags (a list of bools or a numpy bool array) packed for :class:`LidarMask`."""
    if hasattr(values, "astype"):
        return bytes(values.astype("u1").tobytes())
    return bytes(1 if v else 0 for v in values)


def _floats(packed: bytes) -> memoryview[float]:
    if _LITTLE:
        return memoryview(packed).cast("f")
    native = array("f")
    native.frombytes(packed)
    native.byteswap()
    return cast("memoryview[float]", memoryview(native))  # format "f" already


def _check_ranges(packed: bytes) -> None:
    if len(packed) % 4:
        raise ValueError(
            f"ranges holds {len(packed)} bytes, not a whole number of float32 beams "
            "(4 bytes each); pack them with rap_schemas.pack_ranges"
        )
    if not packed:
        return
    import numpy as np  # here: only a scan pays numpy's import

    values = np.frombuffer(packed, "<f4")
    ok = values >= 0  # False for NaN and for negatives
    if not ok.all():
        i = int(np.flatnonzero(~ok)[0])
        raise ValueError(
            f"ranges[{i}] is {float(values[i])!r}; a range is metres >= 0, or inf where "
            "a beam has no return, never NaN nor negative"
        )


def _check_flags(packed: bytes) -> None:
    if packed.translate(None, b"\x00\x01"):  # a byte other than 0 or 1 (C speed)
        i = next(i for i, b in enumerate(packed) if b > 1)
        raise ValueError(
            f"occluded[{i}] is byte {packed[i]}; a packed flag is 0 or 1 "
            "(pack them with rap_schemas.pack_flags)"
        )


class LaserScan(Message, frozen=True):
    TYPE = "rap.LaserScan/2"

    stamp: Nanos
    """Sensor time of the first beam."""
    frame_id: str
    angle_min: Angle
    angle_increment: Increment
    range_min: Metres
    range_max: Metres
    ranges: PackedRanges
    """Metres, packed (:func:`pack_ranges`; read them with :meth:`values`): float32
    little-endian, ``inf`` where a beam has no return (occluded or beyond range); never
    NaN nor negative. Packed, a 360-beam scan decodes without a Python float per beam."""
    scan_time: Seconds = 0.2

    @property
    def beams(self) -> int:
        """The number of beams."""
        return len(self.ranges) // 4

    def values(self) -> memoryview[float]:
        """The ranges as a read-only sequence of floats (no copy on little-endian hosts;
        ``numpy.asarray(scan.values())`` is a float32 array over the same bytes)."""
        return _floats(self.ranges)

    def __post_init__(self) -> None:
        _check_ranges(self.ranges)
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
    """Beam i is judged occluded where ``flags()[i]`` is True."""

    TYPE = "rap.LidarMask/2"

    angle_min: Angle
    angle_increment: Increment
    occluded: PackedFlags
    """One byte per beam, 0 or 1 (:func:`pack_flags`; read them with :meth:`flags`)."""
    frame_id: str = "base_link"

    @property
    def beams(self) -> int:
        """The number of beams."""
        return len(self.occluded)

    def flags(self) -> memoryview[bool]:
        """The flags as a read-only sequence of bools (no copy;
        ``numpy.asarray(mask.flags())`` is a bool array over the same bytes)."""
        return memoryview(self.occluded).cast("?")

    def __post_init__(self) -> None:
        _check_flags(self.occluded)
