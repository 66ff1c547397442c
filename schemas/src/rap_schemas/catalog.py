"""Every wire message type, for schema export and type look-up by wire name.

RAP's own types are known from the start; an application registers its own
(``register(Weather, Pose)``; generated message modules do so on import), so that tools
that decode by wire name (``by_type``) know them too."""

from __future__ import annotations

from typing import Final

from .knowledge import KbRecord
from .lidar import LaserScan, LidarMask, Odometry, Pose2D, SimTime, SpinCommand, SpinPlan, Twist
from .logrecord import LogRecord
from .maplek import Empty, KnowledgeAccess, PlanProposal, Rejection, StageTrace, Verdict
from .message import Message
from .trust import TrustOutput, TrustSpecStatus, TrustSpecUpdate, TrustVerdict

__all__ = ["MESSAGES", "by_type", "register", "registered"]

MESSAGES: Final[tuple[type[Message], ...]] = (
    Empty,
    KbRecord,
    KnowledgeAccess,
    LaserScan,
    LidarMask,
    LogRecord,
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

_BY_TYPE: Final[dict[str, type[Message]]] = {m.TYPE: m for m in MESSAGES}


def register(*messages: type[Message]) -> None:
    """Make application messages known by their wire name. Registering the same class
    again is harmless; another class under a name already taken is a ``ValueError``."""
    for m in messages:
        if not m.TYPE:
            raise ValueError(f"{m.__qualname__} has no TYPE; give it a wire name to register it")
        known = _BY_TYPE.get(m.TYPE)
        if known is not None and known is not m:
            raise ValueError(
                f"wire name {m.TYPE!r} is taken by {known.__module__}.{known.__qualname__}; "
                f"give {m.__module__}.{m.__qualname__} another name or version"
            )
        _BY_TYPE[m.TYPE] = m


def registered() -> dict[str, type[Message]]:
    """Every known wire name and its class (RAP's and the registered ones)."""
    return dict(_BY_TYPE)


def by_type(name: str) -> type[Message]:
    """The message class for a wire name; ``KeyError`` naming the known ones otherwise."""
    try:
        return _BY_TYPE[name]
    except KeyError:
        raise KeyError(f"unknown message type {name!r}; known: {sorted(_BY_TYPE)}") from None
