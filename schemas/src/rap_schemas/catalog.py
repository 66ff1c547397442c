"""Every wire message type, for schema export and type look-up by wire name."""

from __future__ import annotations

from typing import Final

from .knowledge import KbRecord
from .lidar import LaserScan, LidarMask, Odometry, Pose2D, SimTime, SpinCommand, SpinPlan, Twist
from .maplek import Empty, KnowledgeAccess, PlanProposal, Rejection, StageTrace, Verdict
from .message import Message
from .trust import TrustOutput, TrustSpecStatus, TrustSpecUpdate, TrustVerdict

__all__ = ["MESSAGES", "by_type"]

MESSAGES: Final[tuple[type[Message], ...]] = (
    Empty,
    KbRecord,
    KnowledgeAccess,
    LaserScan,
    LidarMask,
    Odometry,
    PlanProposal,
    Pose2D,
    Rejection,
    SimTime,
    SpinCommand,
    SpinPlan,
    StageTrace,
    TrustOutput,
    TrustSpecStatus,
    TrustSpecUpdate,
    TrustVerdict,
    Twist,
    Verdict,
)

_BY_TYPE: Final = {m.TYPE: m for m in MESSAGES}


def by_type(name: str) -> type[Message]:
    """The message class for a wire name; ``KeyError`` naming the known ones otherwise."""
    try:
        return _BY_TYPE[name]
    except KeyError:
        raise KeyError(f"unknown message type {name!r}; known: {sorted(_BY_TYPE)}") from None
