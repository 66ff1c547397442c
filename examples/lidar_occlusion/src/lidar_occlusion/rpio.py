"""RPIO's lidar-occlusion stages in this loop: each stage of :mod:`lidar_occlusion.nodes`
may be the unmodified RPIO 0.4.3 node instead (docs/migrating-from-rpio.md).

The module attributes ``monitor``, ``analysis``, ``planner``, ``legitimate`` and
``executor`` are the RAP nodes that stand for the RPIO nodes of the same stage (for robot
``tb1``; ``build(robot)`` makes a fresh set). A model runs one in place of the RAP stage
by naming it (``module: lidar_occlusion.rpio:analysis``) with the RPIO Redis in its
``config:`` (:class:`rap_bridges.rpio.RpioConfig`), and starts the RPIO node itself as
an ``external`` component with ``run:``. What each one does, with the RPIO events and
knowledge keys of the RoboSAPIENS lidar-occlusion chain:

==========  ==========================  ===================  =======================
stage       RAP trigger -> RPIO         RPIO answer          -> RAP
==========  ==========================  ===================  =======================
monitor     data <robot>/scan ->        event new_data       knowledge laser_scan;
            message /Scan                                    event new-data
analyse     event new-data: laser_scan  event anomaly        knowledge lidar_mask;
            -> Redis; event new_data                         event anomaly (the mask)
plan        event anomaly: lidar_mask   event new_plan       knowledge directions,
            -> Redis; event anomaly                          planned_lidar_mask;
                                                             the plan proposed
legitimate  event new-plan: the plan    event isLegit        verdict (approved; no
            -> Redis directions;                             answer in time: rejected)
            event new_plan
execute     an approved verdict (the    message              data <robot>/spin_config
            gate): the plan -> Redis    /spin_config         (the plan RPIO sent)
            directions; event isLegit
==========  ==========================  ===================  =======================

The codecs below are the RPIO side's JSON shapes: a scan as the ROS-like object of the
RPIO chain (``header`` with ``seq``, ``stamp`` and ``t_send_ns``; ``ranges`` with
``Infinity`` for a beam with no return), a mask as ``{"seq", "t_send_ns", "occluded":
[0|1, ...]}`` and a plan as ``{"commands": [{"omega", "duration"}], "period", "seq",
"t_send_ns"}``. ``seq`` is the request's number (the RPIO chain carries it from its
input to its output); RAP's types are checked on the way back in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Annotated, Any, TypeVar

import msgspec
import numpy as np
from rap_bridges.rpio import RpioConfig, RpioStage
from rap_schemas import (
    LaserScan,
    LidarMask,
    Message,
    PlanProposal,
    SpinPlan,
    pack_flags,
    pack_ranges,
)
from rap_sdk import Context
from rap_sdk.gate import ApprovalGate, legitimate, propose

from .nodes import (
    ANOMALY,
    DIRECTIONS,
    HANDLING,
    LASER_SCAN,
    LIDAR_MASK,
    NEW_DATA,
    PLANNED_MASK,
    ExecuteConfig,
)

__all__ = [
    "RpioLoop",
    "analysis",
    "build",
    "executor",
    "legitimate_node",
    "mask_from_rpio",
    "mask_to_rpio",
    "monitor",
    "plan_from_rpio",
    "plan_to_rpio",
    "planner",
    "scan_from_rpio",
    "scan_to_rpio",
]

# the RPIO chain's events and messages
SCAN_MESSAGE = "/Scan"
PLAN_MESSAGE = "/spin_config"
RPIO_NEW_DATA = "new_data"
RPIO_ANOMALY = "anomaly"
RPIO_NEW_PLAN = "new_plan"
RPIO_IS_LEGIT = "isLegit"

M = TypeVar("M", bound=Message)
Count = Annotated[int, msgspec.Meta(ge=0, le=2**63 - 1)]


# -- the RPIO side's shapes, typed --------------------------------------------------------


class _Stamp(msgspec.Struct):
    secs: Count
    nsecs: Annotated[int, msgspec.Meta(ge=0, lt=1_000_000_000)] = 0


class _Header(msgspec.Struct):
    seq: int | None = None
    stamp: _Stamp | None = None
    frame_id: str = ""
    t_send_ns: Count | None = None


class _Scan(msgspec.Struct):
    header: _Header
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: list[float]
    scan_time: float = 0.2


class _Mask(msgspec.Struct):
    occluded: list[Annotated[int, msgspec.Meta(ge=0, le=1)]]
    angle_min: float | None = None
    angle_increment: float | None = None
    frame_id: str | None = None


class _Command(msgspec.Struct):
    omega: float
    duration: float


class _Plan(msgspec.Struct):
    commands: list[_Command]
    period: float = 8.0


def _typed(value: Any, cls: type[Any], what: str) -> Any:
    """``value`` (parsed JSON) as ``cls``: strict (no str for a number), extra fields
    ignored; ``ValueError`` naming ``what`` and the field otherwise."""
    try:
        return msgspec.convert(value, cls, strict=True)
    except msgspec.ValidationError as exc:
        raise ValueError(f"not an RPIO {what}: {exc}") from None


def _rap(value: dict[str, Any], cls: type[M]) -> M:
    """A RAP message from its fields, with every constraint of its schema checked."""
    try:
        return msgspec.convert(value, cls)
    except msgspec.ValidationError as exc:
        raise ValueError(f"not a valid {cls.TYPE}: {exc}") from None


def scan_to_rpio(scan: LaserScan, seq: int) -> dict[str, Any]:
    """A scan as the RPIO chain's ``laser_scan`` (and ``/Scan``) object."""
    ranges = np.asarray(scan.values(), dtype=np.float64).tolist()
    n = len(ranges)
    return {
        "header": {
            "seq": seq,
            "stamp": {"secs": scan.stamp // 1_000_000_000, "nsecs": scan.stamp % 1_000_000_000},
            "frame_id": scan.frame_id,
            "t_send_ns": scan.stamp,
        },
        "angle_min": scan.angle_min,
        "angle_max": scan.angle_min + scan.angle_increment * max(n - 1, 0),
        "angle_increment": scan.angle_increment,
        "time_increment": 0.0,
        "scan_time": scan.scan_time,
        "range_min": scan.range_min,
        "range_max": scan.range_max,
        "ranges": ranges,
        "intensities": [],
    }


def scan_from_rpio(value: Any) -> LaserScan:
    """An RPIO scan object as a :class:`~rap_schemas.LaserScan` (its stamp from
    ``header.stamp``, else ``header.t_send_ns``, else 0)."""
    s = _typed(value, _Scan, "scan")
    h = s.header
    stamp = (
        h.stamp.secs * 1_000_000_000 + h.stamp.nsecs if h.stamp is not None else h.t_send_ns or 0
    )
    bad = next((i for i, r in enumerate(s.ranges) if math.isnan(r) or r < 0), None)
    if bad is not None:
        raise ValueError(
            f"ranges[{bad}] is {s.ranges[bad]!r}; a range is metres >= 0, or Infinity where a "
            "beam has no return"
        )
    return _rap(
        {
            "stamp": stamp,
            "frame_id": h.frame_id,
            "angle_min": s.angle_min,
            "angle_increment": s.angle_increment,
            "range_min": s.range_min,
            "range_max": s.range_max,
            "ranges": pack_ranges(s.ranges),
            "scan_time": s.scan_time,
        },
        LaserScan,
    )


def mask_to_rpio(mask: LidarMask, seq: int, t_ns: int) -> dict[str, Any]:
    """A mask as the RPIO chain's ``lidar_mask`` object (with its angles, which the RPIO
    chain does not need but a planner may)."""
    return {
        "seq": seq,
        "t_send_ns": t_ns,
        "occluded": list(mask.occluded),
        "angle_min": mask.angle_min,
        "angle_increment": mask.angle_increment,
        "frame_id": mask.frame_id,
    }


def mask_from_rpio(value: Any, scan: LaserScan | None = None) -> LidarMask:
    """An RPIO mask object as a :class:`~rap_schemas.LidarMask`; the angles and frame it
    does not give are those of ``scan`` (the scan it was made from), whose beams it must
    match."""
    m = _typed(value, _Mask, "mask")
    if scan is not None and len(m.occluded) != scan.beams:
        raise ValueError(f"the mask has {len(m.occluded)} flags for a scan of {scan.beams} beams")
    angle_min = m.angle_min if m.angle_min is not None else scan.angle_min if scan else None
    inc = (
        m.angle_increment
        if m.angle_increment is not None
        else scan.angle_increment
        if scan
        else None
    )
    if angle_min is None or inc is None:
        raise ValueError("the mask gives no angle_min and angle_increment, and no scan does")
    fields: dict[str, Any] = {
        "angle_min": angle_min,
        "angle_increment": inc,
        "occluded": pack_flags(m.occluded),
    }
    if m.frame_id is not None:
        fields["frame_id"] = m.frame_id
    return _rap(fields, LidarMask)


def plan_to_rpio(plan: SpinPlan, seq: int, t_ns: int) -> dict[str, Any]:
    """A plan as the RPIO chain's ``directions`` object."""
    return {
        "commands": [{"omega": c.omega, "duration": c.duration} for c in plan.commands],
        "period": plan.period,
        "seq": seq,
        "t_send_ns": t_ns,
    }


def plan_from_rpio(value: Any) -> SpinPlan:
    """An RPIO ``directions`` object as a :class:`~rap_schemas.SpinPlan`."""
    p = _typed(value, _Plan, "plan (directions)")
    commands = [{"omega": c.omega, "duration": c.duration} for c in p.commands]
    return _rap({"commands": commands, "period": p.period}, SpinPlan)


# -- the stages --------------------------------------------------------------------------


@dataclass
class RpioLoop:
    """The five RAP nodes that stand for RPIO's stages (use any of them in place of the
    RAP stage of the same name)."""

    monitor: RpioStage
    analysis: RpioStage
    planner: RpioStage
    legitimate: RpioStage
    executor: RpioStage
    gate: ApprovalGate

    @property
    def stages(self) -> list[RpioStage]:
        return [self.monitor, self.analysis, self.planner, self.legitimate, self.executor]


def build(
    robot: str = "tb1",
    *,
    prefix: str = "",
    config: RpioConfig | None = None,
    execution: ExecuteConfig | None = None,
) -> RpioLoop:
    """A fresh set of the five stand-ins for robot ``robot`` (names start with
    ``prefix``, as :func:`lidar_occlusion.nodes.build`'s), all with ``config``."""
    mon = RpioStage(f"{prefix}monitor", stage="monitor", config=config)
    ana = RpioStage(f"{prefix}analysis", stage="analyse", config=config)
    pla = RpioStage(f"{prefix}planner", stage="plan", config=config)
    leg = RpioStage(f"{prefix}legitimate", stage="legitimate", config=config)
    exe = RpioStage(f"{prefix}executor", stage="execute", config=config)
    exe_cfg = execution or ExecuteConfig()
    gate = ApprovalGate(legitimators={leg.name}, max_age=exe_cfg.max_age)
    spin_topic = f"{robot}/spin_config"

    @mon.node.on_data(f"{robot}/scan")
    async def on_scan(ctx: Context, scan: LaserScan) -> None:
        req = mon.request(ctx)
        reply = await req.call(
            message=SCAN_MESSAGE,
            payload=scan_to_rpio(scan, req.seq),
            answer=RPIO_NEW_DATA,
            take={LASER_SCAN: scan_from_rpio},
        )
        if reply:
            await ctx.kb.write(LASER_SCAN, reply.values[LASER_SCAN])
            await ctx.emit(NEW_DATA)

    @ana.node.on_event(NEW_DATA)
    async def detect(ctx: Context) -> None:
        scan = await ctx.kb.read(LASER_SCAN, LaserScan)
        req = ana.request(ctx)
        reply = await req.call(
            write={LASER_SCAN: scan_to_rpio(scan, req.seq)},
            event=RPIO_NEW_DATA,
            answer=RPIO_ANOMALY,
            take={LIDAR_MASK: partial(mask_from_rpio, scan=scan)},
        )
        if reply:
            mask: LidarMask = reply.values[LIDAR_MASK]
            await ctx.kb.write(LIDAR_MASK, mask)
            await ctx.emit(ANOMALY, mask)

    @pla.node.on_event(ANOMALY, type=LidarMask)
    async def make_plan(ctx: Context) -> None:
        mask = await ctx.kb.read(LIDAR_MASK, LidarMask)
        req = pla.request(ctx)
        reply = await req.call(
            write={LIDAR_MASK: mask_to_rpio(mask, req.seq, ctx.clock.time_ns())},
            event=RPIO_ANOMALY,
            answer=RPIO_NEW_PLAN,
            take={DIRECTIONS: plan_from_rpio},
        )
        if reply:
            spin: SpinPlan = reply.values[DIRECTIONS]
            # as RAP's planner: the mask this plan answers (RAP's analysis reads it)
            await ctx.kb.write(PLANNED_MASK, mask)
            await ctx.kb.write(DIRECTIONS, spin)
            await propose(ctx, spin)

    @legitimate(leg.node)
    async def check(ctx: Context, proposal: PlanProposal[SpinPlan]) -> str | None:
        req = leg.request(ctx)
        reply = await req.call(
            write={DIRECTIONS: plan_to_rpio(proposal.plan, req.seq, proposal.created)},
            event=RPIO_NEW_PLAN,
            data={"plan_uid": proposal.plan_uid.hex()},
            answer=RPIO_IS_LEGIT,
        )
        return None if reply else f"RPIO Legitimate: {reply.reason}"

    @gate.on_approved(exe.node)
    async def act(ctx: Context, proposal: PlanProposal[SpinPlan]) -> None:
        req = exe.request(ctx)
        reply = await req.call(
            write={DIRECTIONS: plan_to_rpio(proposal.plan, req.seq, proposal.created)},
            event=RPIO_IS_LEGIT,
            data={"plan_uid": proposal.plan_uid.hex()},
            answer_message=PLAN_MESSAGE,
            decode=plan_from_rpio,
        )
        if reply:
            await ctx.publish(spin_topic, reply.answer)
            await ctx.kb.write(HANDLING, False)

    return RpioLoop(mon, ana, pla, leg, exe, gate)


_default = build()
monitor = _default.monitor.node
analysis = _default.analysis.node
planner = _default.planner.node
legitimate_node = _default.legitimate.node
executor = _default.executor.node
