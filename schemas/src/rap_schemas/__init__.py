"""rap_schemas: every wire message, the envelope and the key space of RAP."""

from . import keys
from .catalog import MESSAGES, by_type
from .envelope import Envelope
from .knowledge import (
    MODELS_PREFIX,
    KbDelete,
    KbGet,
    KbHistory,
    KbList,
    KbPut,
    KbRecord,
    KbReply,
    KbRequest,
    ModelGet,
    ModelList,
    ModelMeta,
    ModelPin,
    ModelPut,
)
from .lidar import (
    Empty,
    LaserScan,
    LidarMask,
    Odometry,
    PlanProposal,
    Pose2D,
    SimTime,
    SpinCommand,
    SpinPlan,
    Twist,
    Verdict,
)
from .maplek import KnowledgeAccess, Rejection, Stage, StageTrace
from .message import Message

__all__ = [
    "MESSAGES",
    "MODELS_PREFIX",
    "Empty",
    "Envelope",
    "KbDelete",
    "KbGet",
    "KbHistory",
    "KbList",
    "KbPut",
    "KbRecord",
    "KbReply",
    "KbRequest",
    "KnowledgeAccess",
    "LaserScan",
    "LidarMask",
    "Message",
    "ModelGet",
    "ModelList",
    "ModelMeta",
    "ModelPin",
    "ModelPut",
    "Odometry",
    "PlanProposal",
    "Pose2D",
    "Rejection",
    "SimTime",
    "SpinCommand",
    "SpinPlan",
    "Stage",
    "StageTrace",
    "Twist",
    "Verdict",
    "by_type",
    "keys",
]
