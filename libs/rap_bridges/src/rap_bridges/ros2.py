"""ROS 2 messages as DDS carries them, and their mapping to RAP's (docs/bridges/dds.md).

The types are ``cyclonedds.idl`` dataclasses with ROS 2's DDS type names and fields, in
ROS 2's order and widths, so that their CDR (XCDR1, as ROS 2 writes it) is the bytes a
ROS 2 node sends: ``sensor_msgs/msg/LaserScan`` is the DDS type
``sensor_msgs::msg::dds_::LaserScan_``, with its ``std_msgs/msg/Header`` and
``builtin_interfaces/msg/Time``; ``std_msgs``' ``Bool``, ``Int64``, ``Float64`` and
``String`` too (the trust checker's inputs). Two RAP messages of their own:
``rap_msgs/msg/SpinPlan`` (RAP's ``rap.SpinPlan/1``) and ``rap_msgs/msg/Frame``, the
generic frame that carries formats ``envelope``, ``json`` and ``raw`` (headers and
payload bytes)::

    # rap_msgs/msg/SpinCommand.msg      # rap_msgs/msg/SpinPlan.msg
    float64 omega      # rad/s          SpinCommand[] commands
    float64 duration   # s              float64 period   # s

    # rap_msgs/msg/FrameHeader.msg      # rap_msgs/msg/Frame.msg
    string key                          FrameHeader[] headers
    string value                        uint8[] payload

The mapping (:data:`MAPPINGS`, by RAP wire type): :func:`to_ros` turns a RAP message into
its ROS 2 message, :func:`from_ros` a ROS 2 message into the builtins of the RAP message
(the caller validates them against the RAP type: ``msgspec.convert`` or a decoder). What
does not map is said here and in the docs; a value that cannot be represented raises
:class:`Unrepresentable` with the reason.

- Stamps: RAP's integer nanoseconds <-> ``sec`` (int32) and ``nanosec`` (uint32). A
  stamp past 2038-01-19 (int32 seconds) or a negative one cannot be represented.
- ``rap.LaserScan/2`` <-> ``sensor_msgs/msg/LaserScan``: out, ``angle_max`` is
  ``angle_min + (beams - 1) * angle_increment``, ``time_increment`` is 0 (unknown) and
  ``intensities`` is empty; floats are rounded to float32. In, ``angle_max``,
  ``time_increment`` and ``intensities`` are dropped; a scan with a negative
  ``angle_increment`` (a clockwise lidar) is reversed so that angles grow (its stamp
  moves to the first beam of the new order when ``time_increment`` is known); a NaN
  range (REP 117: no valid return) becomes ``inf`` (no return) and ``-inf`` (closer
  than ``range_min``) becomes 0. A negative finite range is refused (by the RAP type).
- ``rap.Twist/1`` <-> ``geometry_msgs/msg/Twist``: ``linear`` is ``linear.x``,
  ``angular`` is ``angular.z``; in, a twist with any other component non-zero is
  refused (RAP's twist is planar).
- ``rap.Odometry/1`` <-> ``nav_msgs/msg/Odometry``: ``pose`` is ``position.x``/``.y``
  and the yaw of ``orientation``; out, z, roll and pitch are 0, ``child_frame_id`` is
  empty and the covariances are zero (unknown); in, the pose is projected on the plane
  (z, roll, pitch, the other twist components, ``child_frame_id`` and the covariances
  are dropped); an orientation that is not a unit quaternion is refused.
- ``rap.SpinPlan/1`` <-> ``rap_msgs/msg/SpinPlan``: field for field.
- ``frame_id`` is carried as it is; a string holding a NUL character cannot be.

The envelope's ``cycle`` and ``cause`` have no place in a ROS 2 message: only the generic
frame carries them (in its headers); ``frame_id`` is never used for them.
"""

# No "from __future__ import annotations": cyclonedds reads the fields' annotations as
# objects.
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Annotated, Any, Final

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float32, float64, int32, int64, sequence, uint8, uint32
from rap_schemas import LaserScan, Message, Odometry, SpinPlan, Twist, pack_ranges

__all__ = [
    "MAPPINGS",
    "Bool_",
    "Float64_",
    "FrameHeader_",
    "Frame_",
    "Header_",
    "Int64_",
    "LaserScan_",
    "Odometry_",
    "RosMapping",
    "SpinCommand_",
    "SpinPlan_",
    "String_",
    "Time_",
    "Twist_",
    "Unrepresentable",
    "dds_topic",
    "from_ros",
    "mapping_for",
    "ros_name",
    "to_ros",
]

TOPIC_PREFIX: Final = "rt"
"""ROS 2's prefix of the DDS topics of its topics (``/scan`` is ``rt/scan``)."""
INT32_MAX: Final = 2**31 - 1
NS: Final = 1_000_000_000
PLANAR_EPS: Final = 1e-9
"""How far from 0 a component RAP's planar messages do not have may be."""
UNIT_EPS: Final = 1e-3
"""How far from 1 the norm of an orientation quaternion may be."""

Float32s = Annotated[Sequence[float], sequence(float32)]
Octets = Annotated[Sequence[int], sequence(uint8)]
Covariance = Annotated[Sequence[float], array(float64, 36)]


class Unrepresentable(ValueError):
    """A value the other side's message cannot hold; ``reason`` says which and why."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


# -- ROS 2's messages (DDS type names and fields as ROS 2 generates them) -------------------


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
    ranges: Float32s
    intensities: Float32s


@dataclass
class Vector3_(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Twist_(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3_
    angular: Vector3_


@dataclass
class Point_(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion_(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Pose_(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point_
    orientation: Quaternion_


@dataclass
class PoseWithCovariance_(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose_
    covariance: Covariance


@dataclass
class TwistWithCovariance_(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    twist: Twist_
    covariance: Covariance


@dataclass
class Odometry_(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    header: Header_
    child_frame_id: str
    pose: PoseWithCovariance_
    twist: TwistWithCovariance_


@dataclass
class Bool_(IdlStruct, typename="std_msgs::msg::dds_::Bool_"):
    data: bool


@dataclass
class Int64_(IdlStruct, typename="std_msgs::msg::dds_::Int64_"):
    data: int64


@dataclass
class Float64_(IdlStruct, typename="std_msgs::msg::dds_::Float64_"):
    data: float64


@dataclass
class String_(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str


# -- RAP's own ROS 2 messages -----------------------------------------------------------------


@dataclass
class SpinCommand_(IdlStruct, typename="rap_msgs::msg::dds_::SpinCommand_"):
    omega: float64
    duration: float64


@dataclass
class SpinPlan_(IdlStruct, typename="rap_msgs::msg::dds_::SpinPlan_"):
    commands: Annotated[Sequence[SpinCommand_], sequence(SpinCommand_)]
    period: float64


@dataclass
class FrameHeader_(IdlStruct, typename="rap_msgs::msg::dds_::FrameHeader_"):
    key: str
    value: str


@dataclass
class Frame_(IdlStruct, typename="rap_msgs::msg::dds_::Frame_"):
    """A message in format envelope, json or raw, with its headers (``rap-type``,
    ``rap-source``, ``rap-cycle``, ``rap-cause``)."""

    headers: Annotated[Sequence[FrameHeader_], sequence(FrameHeader_)]
    payload: Octets


# -- names ----------------------------------------------------------------------------------


def ros_name(ros: type[IdlStruct]) -> str:
    """ROS 2's name of a message type: ``sensor_msgs/msg/LaserScan`` for
    ``sensor_msgs::msg::dds_::LaserScan_``."""
    typename: str = ros.__idl_typename__
    package, kind, _, name = typename.split("::")
    return f"{package}/{kind}/{name.removesuffix('_')}"


def dds_topic(address: str) -> str:
    """The DDS topic of a ROS 2 topic name: ``rt/scan`` for ``/scan``."""
    return TOPIC_PREFIX + address


# -- conversions ----------------------------------------------------------------------------


def _text(value: str, what: str) -> str:
    if "\x00" in value:
        raise Unrepresentable(f"{what} holds a NUL character, which a ROS 2 string cannot")
    return value


def _stamp_out(ns: int, what: str) -> Time_:
    sec, nanosec = divmod(ns, NS)
    if not 0 <= sec <= INT32_MAX:
        raise Unrepresentable(
            f"{what} {ns} ns does not fit ROS 2's builtin_interfaces/Time (int32 seconds "
            "since the epoch: 1970 to 2038-01-19)"
        )
    return Time_(sec=sec, nanosec=nanosec)


def _stamp_in(t: Time_, what: str) -> int:
    if t.sec < 0:
        raise Unrepresentable(
            f"{what}.sec is {t.sec}: RAP stamps are nanoseconds since the epoch, never negative"
        )
    if t.nanosec >= NS:
        raise Unrepresentable(f"{what}.nanosec is {t.nanosec}: it must be below 1e9")
    return t.sec * NS + t.nanosec


def _finite(what: str, *values: float) -> None:
    for v in values:
        if not math.isfinite(v):
            raise Unrepresentable(f"{what} is {v}: RAP takes finite numbers only")


def _scan_out(scan: LaserScan) -> LaserScan_:
    ranges = list(scan.values())
    n = len(ranges)
    return LaserScan_(
        header=Header_(
            stamp=_stamp_out(scan.stamp, "stamp"), frame_id=_text(scan.frame_id, "frame_id")
        ),
        angle_min=scan.angle_min,
        angle_max=scan.angle_min + max(n - 1, 0) * scan.angle_increment,
        angle_increment=scan.angle_increment,
        time_increment=0.0,
        scan_time=scan.scan_time,
        range_min=scan.range_min,
        range_max=scan.range_max,
        ranges=ranges,
        intensities=[],
    )


def _scan_in(msg: LaserScan_) -> dict[str, Any]:
    import numpy as np  # only a scan pays numpy's import

    stamp = _stamp_in(msg.header.stamp, "header.stamp")
    inc, angle_min = float(msg.angle_increment), float(msg.angle_min)
    _finite("angle_min or angle_increment", angle_min, inc)
    ranges = np.asarray(msg.ranges, dtype="<f4")
    n = len(ranges)
    if inc < 0:  # a clockwise lidar: reversed, so that angles grow as RAP's do
        ranges = ranges[::-1]
        angle_min += (n - 1) * inc
        inc = -inc
        step = float(msg.time_increment)
        if math.isfinite(step) and step > 0:
            stamp += round((n - 1) * step * NS)
            if stamp >= 2**63:
                raise Unrepresentable(
                    f"time_increment {step} puts the last beam's time past 2262 (an int64 "
                    "of nanoseconds)"
                )
    ranges = np.where(np.isnan(ranges), np.float32(np.inf), ranges)
    ranges = np.where(np.isneginf(ranges), np.float32(0.0), ranges)
    return {
        "stamp": stamp,
        "frame_id": msg.header.frame_id,
        "angle_min": angle_min,
        "angle_increment": inc,
        "range_min": float(msg.range_min),
        "range_max": float(msg.range_max),
        "ranges": pack_ranges(ranges),
        "scan_time": float(msg.scan_time),
    }


def _twist_out(t: Twist) -> Twist_:
    return Twist_(linear=Vector3_(t.linear, 0.0, 0.0), angular=Vector3_(0.0, 0.0, t.angular))


def _planar(t: Twist_, what: str) -> dict[str, Any]:
    for name, v in (
        ("linear.y", t.linear.y),
        ("linear.z", t.linear.z),
        ("angular.x", t.angular.x),
        ("angular.y", t.angular.y),
    ):
        if not abs(v) <= PLANAR_EPS:  # NaN too
            raise Unrepresentable(
                f"{what}{name} is {v}: RAP's twist is planar (linear.x and angular.z only)"
            )
    return {"linear": t.linear.x, "angular": t.angular.z}


def _twist_in(t: Twist_) -> dict[str, Any]:
    return _planar(t, "")


def _odometry_out(o: Odometry) -> Odometry_:
    half = o.pose.theta / 2
    return Odometry_(
        header=Header_(stamp=_stamp_out(o.stamp, "stamp"), frame_id=_text(o.frame_id, "frame_id")),
        child_frame_id="",
        pose=PoseWithCovariance_(
            pose=Pose_(
                position=Point_(o.pose.x, o.pose.y, 0.0),
                orientation=Quaternion_(0.0, 0.0, math.sin(half), math.cos(half)),
            ),
            covariance=[0.0] * 36,
        ),
        twist=TwistWithCovariance_(twist=_twist_out(o.twist), covariance=[0.0] * 36),
    )


def _odometry_in(o: Odometry_) -> dict[str, Any]:
    q = o.pose.pose.orientation
    p = o.pose.pose.position
    _finite("pose.pose.orientation", q.x, q.y, q.z, q.w)
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    if abs(norm - 1) > UNIT_EPS:
        raise Unrepresentable(
            f"pose.pose.orientation has norm {norm:.6g}: an orientation is a unit quaternion"
        )
    yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
    twist = o.twist.twist
    return {
        "stamp": _stamp_in(o.header.stamp, "header.stamp"),
        "frame_id": o.header.frame_id,
        "pose": {"x": p.x, "y": p.y, "theta": yaw},
        "twist": {"linear": twist.linear.x, "angular": twist.angular.z},
    }


def _plan_out(plan: SpinPlan) -> SpinPlan_:
    commands = [SpinCommand_(omega=c.omega, duration=c.duration) for c in plan.commands]
    return SpinPlan_(commands=commands, period=plan.period)


def _plan_in(plan: SpinPlan_) -> dict[str, Any]:
    return {
        "commands": [{"omega": c.omega, "duration": c.duration} for c in plan.commands],
        "period": plan.period,
    }


@dataclass(frozen=True, slots=True)
class RosMapping:
    """One RAP message type and the ROS 2 message it is carried as."""

    rap: type[Message]
    ros: type[IdlStruct]
    to_ros: Callable[[Any], IdlStruct]
    from_ros: Callable[[Any], dict[str, Any]]

    @property
    def ros_name(self) -> str:
        return ros_name(self.ros)


MAPPINGS: Final[dict[str, RosMapping]] = {
    m.rap.TYPE: m
    for m in (
        RosMapping(LaserScan, LaserScan_, _scan_out, _scan_in),
        RosMapping(Twist, Twist_, _twist_out, _twist_in),
        RosMapping(Odometry, Odometry_, _odometry_out, _odometry_in),
        RosMapping(SpinPlan, SpinPlan_, _plan_out, _plan_in),
    )
}
"""RAP wire type -> its ROS 2 message."""


def mapping_for(message: type[Message] | None) -> RosMapping:
    """The ROS 2 message of a RAP type; ``ValueError`` saying what to write when it has
    none."""
    known = ", ".join(f"{t} ({m.ros_name})" for t, m in MAPPINGS.items())
    if message is None:
        raise ValueError(f"format cdr needs the port's message type; it maps {known}")
    try:
        return MAPPINGS[message.TYPE]
    except KeyError:
        raise ValueError(
            f"format cdr: {message.TYPE} has no ROS 2 message; cdr maps {known} - use "
            "format json (carried in rap_msgs/msg/Frame)"
        ) from None


def to_ros(message: Message) -> IdlStruct:
    """The ROS 2 message of a RAP message; :class:`Unrepresentable` when a value does not
    fit it, ``ValueError`` when its type has no ROS 2 message."""
    return mapping_for(type(message)).to_ros(message)


def from_ros(sample: IdlStruct, message: type[Message]) -> dict[str, Any]:
    """The builtins of the RAP message ``message`` that a ROS 2 message stands for (to be
    validated by the caller against the type); :class:`Unrepresentable` when a value has
    no RAP equivalent."""
    mapping = mapping_for(message)
    if not isinstance(sample, mapping.ros):
        raise Unrepresentable(
            f"expected a {mapping.ros_name}, got a {type(sample).__name__.removesuffix('_')}"
        )
    return mapping.from_ros(sample)
