"""Messages of the lidar-occlusion case (shared/reference/lidar-occlusion.md).

Angles are radians in the robot's base frame (x forward, counter-clockwise positive);
the lidar mount offset, if any, is applied by the publisher and named in ``frame_id``.
"""

from __future__ import annotations

from .message import Message

__all__ = [
    "Empty",
    "LaserScan",
    "LidarMask",
    "Odometry",
    "PlanProposal",
    "Pose2D",
    "SimTime",
    "SpinCommand",
    "SpinPlan",
    "Twist",
    "Verdict",
]


class Empty(Message, frozen=True):
    """A body-less event."""

    TYPE = "rap.Empty/1"


class LaserScan(Message, frozen=True):
    TYPE = "rap.LaserScan/1"

    stamp: int
    """Sensor time of the first beam, integer nanoseconds."""
    frame_id: str
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: list[float]
    """Metres; ``inf`` where a beam has no return (occluded or beyond range)."""
    scan_time: float = 0.2


class Pose2D(Message, frozen=True):
    TYPE = "rap.Pose2D/1"

    x: float
    y: float
    theta: float


class Twist(Message, frozen=True):
    """Planar velocity command: forward m/s and yaw rate rad/s."""

    TYPE = "rap.Twist/1"

    linear: float
    angular: float


class Odometry(Message, frozen=True):
    TYPE = "rap.Odometry/1"

    stamp: int
    frame_id: str
    pose: Pose2D
    twist: Twist


class SimTime(Message, frozen=True):
    """The simulator's clock (``rap/<system>/data/clock``): sim time, ns."""

    TYPE = "rap.SimTime/1"

    t: int
    realtime_factor: float = 0.0
    """0 in lockstep (as fast as possible), else sim seconds per wall second."""


class SpinCommand(Message, frozen=True):
    """Turn in place at ``omega`` rad/s for ``duration`` s."""

    TYPE = "rap.SpinCommand/1"

    omega: float
    duration: float


class SpinPlan(Message, frozen=True):
    """Every ``period`` s the robot runs ``commands`` in order, then resumes nominal
    navigation; an empty plan restores nominal behaviour."""

    TYPE = "rap.SpinPlan/1"

    commands: list[SpinCommand]
    period: float = 8.0


class LidarMask(Message, frozen=True):
    """``occluded[i]`` is True where beam i is judged occluded."""

    TYPE = "rap.LidarMask/1"

    angle_min: float
    angle_increment: float
    occluded: list[bool]
    frame_id: str = "base_link"


class PlanProposal(Message, frozen=True):
    """A plan put to the Legitimate stage."""

    TYPE = "rap.PlanProposal/1"

    plan_uid: bytes
    plan: SpinPlan
    proposer: str
    created: int
    """UTC ns when the plan was made; legitimation rejects stale plans."""


class Verdict(Message, frozen=True, omit_defaults=True):
    """The Legitimate stage's decision on one plan.

    An approving verdict carries the proposal it approves: the execute side acts on
    exactly that plan, never on whatever a knowledge key holds by then."""

    TYPE = "rap.Verdict/1"

    plan_uid: bytes
    approved: bool
    legitimator: str
    ts: int
    reason: str = ""
    proposal: PlanProposal | None = None
