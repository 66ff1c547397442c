"""rap_schemas: every wire message, the envelope and the key space of RAP."""

from . import keys
from .catalog import MESSAGES, by_type
from .envelope import Envelope
from .lidar import (
    Empty,
    LaserScan,
    LidarMask,
    Odometry,
    PlanProposal,
    Pose2D,
    SpinCommand,
    SpinPlan,
    Twist,
    Verdict,
)
from .maplek import KnowledgeAccess, Rejection, Stage, StageTrace
from .message import Message, type_name

__all__ = [
    "MESSAGES",
    "Empty",
    "Envelope",
    "KnowledgeAccess",
    "LaserScan",
    "LidarMask",
    "Message",
    "Odometry",
    "PlanProposal",
    "Pose2D",
    "Rejection",
    "SpinCommand",
    "SpinPlan",
    "Stage",
    "StageTrace",
    "Twist",
    "Verdict",
    "by_type",
    "keys",
    "type_name",
]
