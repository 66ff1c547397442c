"""``rap view``: a running system, live, in a Rerun viewer (or an ``.rrd`` file).

It follows the system's data (scans, odometry, plans to the robot), events, trace
records, trust outputs and rejection records, decodes each by its wire type and logs it
to Rerun with the entity layout of the demo's own recording (``sim_world.viz`` and the
lidar case's observer), so the live view and ``make demo``'s ``demo.rrd`` look alike:

    world/room, world/obstacles/...      the world's static geometry (when it is known)
    world/<robot>/pose, heading, path    from its odometry
    world/<robot>/scan                   lidar returns in the world frame
    world/<robot>/anomaly                the beams an ``anomaly`` flagged, red near the robot
    world/<robot>/plans                  plans that reached the robot
    maplek/<robot>/cycles                "cycle #n: plan at the robot"
    maplek/<stage>                       one line per handler call (its trace record)
    maplek/events/<name>                 every event, with its uid, cycle and cause (hex)
    data/<topic>                         other data (the simulator's clock as a scalar)
    trust/<stream>                       trust outputs (numbers as scalars), verdicts
    log/<node>                           samples a node refused

Timelines: ``time`` (the envelope's ts, UTC), ``cycle`` (the loop cycle a sample belongs
to, numbered in the order the cycles started) and ``sim`` (a simulator's clock: the
stamp of the cycle's scan, as in the demo's recording).

The event loop only decodes; every Rerun call (file, network) runs on one worker thread
fed through a bounded queue: a sample that finds the queue full is dropped and counted.
A sample that cannot be decoded is rejected with its reason, counted, and the view goes
on.
"""

from __future__ import annotations

import functools
import math
import os
import queue
import shutil
import signal
import sys
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Final

import msgspec
import typer

from .cli import failed, usage
from .reach import (
    Reach,
    Where,
    open_fabric,
    reach_options,
)

if TYPE_CHECKING:
    import numpy as np
    import rerun as rr_mod
    from rap_schemas import DeploymentPlan
    from sim_world.world import WorldSpec

__all__ = [
    "Arrows",
    "Log",
    "Points",
    "Scalar",
    "Strips",
    "Text",
    "Translator",
    "Values",
    "Writer",
    "register",
]

QUEUE_BATCHES: Final = 4096
"""Samples (each a batch of log calls) waiting for the Rerun thread; past it, dropped."""
INBOX_SAMPLES: Final = 8192
INBOX_BYTES: Final = 64 << 20
PATH_POINTS: Final = 2000
"""Poses kept per robot for its path line."""
OCCLUDED_MARK: Final = 0.35
"""Metres from the robot where a flagged beam is drawn (as ``sim_world.viz`` does)."""
ROBOT_RADIUS: Final = 0.17
SIM_STAMP_LIMIT: Final = 10**17
"""A sensor stamp below this (about 3 years in ns) is a simulator's clock, not UTC."""
TEXT_CHARS: Final = 300
CYCLES_KEPT: Final = 100_000
DRAIN_QUIET: Final = 0.25
DRAIN_MAX: Final = 3.0
"""On stop: samples still arriving are taken until none came for DRAIN_QUIET s (at
most DRAIN_MAX s)."""
SCAN_GREEN: Final = (40, 180, 90)
FLAG_RED: Final = (220, 40, 40)

# -- what the event loop hands the Rerun thread ------------------------------------------


@dataclass(frozen=True, slots=True)
class Points:
    positions: np.ndarray[Any, np.dtype[np.float64]]
    radius: float | np.ndarray[Any, np.dtype[np.float64]]
    """One radius for every point, or one per point."""
    color: tuple[int, int, int] | None = None


@dataclass(frozen=True, slots=True)
class Arrows:
    origins: list[tuple[float, float]]
    vectors: list[tuple[float, float]]


@dataclass(frozen=True, slots=True)
class Strips:
    strips: list[list[tuple[float, float]]]


@dataclass(frozen=True, slots=True)
class Text:
    text: str
    level: str = "INFO"


@dataclass(frozen=True, slots=True)
class Scalar:
    value: float


@dataclass(frozen=True, slots=True)
class Values:
    """Extra fields shown with an entity (uid, cycle and cause as hex, ...)."""

    values: dict[str, str | int | float | bool]


Visual = Points | Arrows | Strips | Text | Scalar | Values


@dataclass(frozen=True, slots=True)
class Log:
    """One Rerun log call: an entity (its unescaped path parts), what to show, and when."""

    entity: tuple[str, ...]
    items: tuple[Visual, ...]
    ts: int | None = None
    """The envelope's ts, UTC ns (timeline ``time``)."""
    cycle: int | None = None
    """The cycle's number (timeline ``cycle``)."""
    sim_ns: int | None = None
    """Simulated time, ns (timeline ``sim``)."""
    static: bool = False


# -- decoding ----------------------------------------------------------------------------


class _Rejected(Exception):
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _hex(uid: bytes | None) -> str:
    return uid.hex() if uid else ""


def _short(uid: bytes | None) -> str:
    """The last 8 hex digits: a UUIDv7 begins with its millisecond timestamp, shared by
    every uid of the same minute or so, and ends with its per-message counter."""
    return uid.hex()[-8:] if uid else "-"


def _clip(text: str) -> str:
    return text if len(text) <= TEXT_CHARS else text[: TEXT_CHARS - 3] + "..."


@dataclass
class _Pose:
    x: float
    y: float
    theta: float


@dataclass
class _PendingScan:
    env: Any
    scan: Any
    robot: str


@dataclass
class Translator:
    """Decodes fabric samples of one system and turns them into :class:`Log` calls.

    Pure Python and numpy, no Rerun: the event loop runs it. :meth:`sample` raises
    nothing but ``_Rejected`` for a bad sample (see :meth:`take`, which counts)."""

    system: str
    cycle_keys: set[str] = field(default_factory=set)
    """Data keys whose samples start a loop cycle (the monitors' inputs); learned too,
    from the ``cycle`` of later samples."""
    world: WorldSpec | None = None
    viewed: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    """Rejections by reason."""
    _cycles: OrderedDict[bytes, int] = field(default_factory=OrderedDict)
    _next_cycle: int = 0
    _uncycled: OrderedDict[bytes, str] = field(default_factory=OrderedDict)
    _cycle_robot: OrderedDict[bytes, tuple[str, _Pose | None, int | None]] = field(
        default_factory=OrderedDict
    )
    _poses: dict[str, _Pose] = field(default_factory=dict)
    _paths: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    _pending: dict[str, _PendingScan] = field(default_factory=dict)
    _decoders: dict[str, msgspec.msgpack.Decoder[Any]] = field(default_factory=dict)
    _opener: Any = None

    def __post_init__(self) -> None:
        from rap_sdk.envelope import Opener

        self._opener = Opener()

    # -- entry points ---------------------------------------------------------------------
    def take(self, key: str, payload: bytes) -> list[Log]:
        """The log calls for one sample; a bad sample is counted under its reason and
        gives none."""
        try:
            out = self.sample(key, payload)
        except _Rejected as exc:
            self.rejected[exc.reason[:160]] += 1
            if len(self.rejected) > 256:  # bound the reasons kept, not the count
                self.rejected = Counter(dict(self.rejected.most_common(128)))
            return []
        self.viewed += 1
        return out

    def sample(self, key: str, payload: bytes) -> list[Log]:
        from rap_schemas import keys
        from rap_schemas.limits import MAX_SAMPLE_BYTES
        from rap_sdk.errors import RejectedSample

        if len(payload) > MAX_SAMPLE_BYTES:
            raise _Rejected(f"{key}: sample of {len(payload)} bytes (at most {MAX_SAMPLE_BYTES})")
        try:
            parsed = keys.parse(key)
        except keys.KeyError_ as exc:
            raise _Rejected(f"bad key: {exc}") from None
        try:
            env = self._opener.open(key, payload)
        except RejectedSample as exc:
            raise _Rejected(f"{key}: {exc}") from None
        if env is None:
            return []  # a duplicate
        body = self._body(key, env)
        kind, name = parsed.kind, parsed.name
        cycle = self._cycle_of(env, key, kind is keys.Kind.DATA)
        if kind is keys.Kind.DATA:
            return self._data(name, env, body, cycle)
        if kind is keys.Kind.EVENT:
            return self._event(name, env, body, cycle)
        if kind is keys.Kind.TRACE:
            return self._trace(env, body, cycle)
        if kind is keys.Kind.TRUST:
            return self._trust(name, env, body, cycle)
        if kind is keys.Kind.LOG:
            return self._log(name, env, body, cycle)
        return []

    def static(self) -> list[Log]:
        """The world's geometry (nothing when the world is not known)."""
        import numpy as np

        w = self.world
        if w is None:
            return []
        from sim_world.world import Box, Circle

        out = [
            Log(
                ("world", "room"),
                (
                    Strips(
                        [
                            [
                                (0.0, 0.0),
                                (w.room.width, 0.0),
                                (w.room.width, w.room.height),
                                (0.0, w.room.height),
                                (0.0, 0.0),
                            ]
                        ]
                    ),
                ),
                static=True,
            )
        ]
        circles = [o for o in w.obstacles if isinstance(o, Circle)]
        if circles:
            out.append(
                Log(
                    ("world", "obstacles", "circles"),
                    (
                        Points(
                            np.array([(c.x, c.y) for c in circles], dtype=np.float64),
                            np.array([c.r for c in circles], dtype=np.float64),
                        ),
                    ),
                    static=True,
                )
            )
        boxes = [o for o in w.obstacles if isinstance(o, Box)]
        if boxes:
            out.append(
                Log(
                    ("world", "obstacles", "boxes"),
                    (Strips([[*b.corners(), b.corners()[0]] for b in boxes]),),
                    static=True,
                )
            )
        return out

    def flush(self) -> list[Log]:
        """Scans still waiting for their pose, logged with the latest one known."""
        out: list[Log] = []
        for robot in list(self._pending):
            out.extend(self._emit_scan(self._pending.pop(robot), self._poses.get(robot)))
        return out

    # -- decoding helpers ---------------------------------------------------------------
    def _body(self, key: str, env: Any) -> Any:
        from rap_schemas import by_type
        from rap_schemas.limits import DECODE_ERRORS, DecodeRejected, check_depth, decode_failure

        dec = self._decoders.get(env.type)
        if dec is None:
            try:
                cls: Any = by_type(env.type)
            except KeyError:
                cls = None
            if cls is None:
                try:
                    return check_depth(msgspec.msgpack.decode(env.body), what=f"{env.type} body")
                except DecodeRejected as exc:
                    raise _Rejected(f"{key}: {exc.reason}") from None
                except DECODE_ERRORS as exc:
                    raise _Rejected(
                        f"{key}: invalid {env.type} body: {decode_failure(exc)}"
                    ) from None
            if len(self._decoders) >= 256:
                self._decoders.clear()
            dec = self._decoders[env.type] = msgspec.msgpack.Decoder(cls)
        try:
            return dec.decode(env.body)
        except DECODE_ERRORS as exc:
            raise _Rejected(f"{key}: invalid {env.type} body: {decode_failure(exc)}") from None

    def _cycle_of(self, env: Any, key: str, data: bool) -> int | None:
        """The number of the cycle ``env`` belongs to (None: none). A sample with a
        ``cycle`` belongs to it; a data sample without one starts a cycle when its key
        is one that starts cycles (a monitor's input, or a key whose samples later
        samples named as their cycle)."""
        cid = env.cycle
        if cid:
            n = self._cycles.get(cid)
            if n is None:
                n = self._new_cycle(cid)
                started = self._uncycled.pop(cid, None)
                if started is not None:
                    self.cycle_keys.add(started)  # learned: this key starts cycles
            return n
        if not data:
            return None
        n = self._cycles.get(env.uid)
        if n is not None:  # a sample of its cycle came first
            self.cycle_keys.add(key)
            return n
        if key in self.cycle_keys:
            return self._new_cycle(env.uid)
        self._uncycled[env.uid] = key
        if len(self._uncycled) > 4096:
            self._uncycled.popitem(last=False)
        return None

    def _new_cycle(self, cid: bytes) -> int:
        n = self._cycles[cid] = self._next_cycle
        self._next_cycle += 1
        if len(self._cycles) > CYCLES_KEPT:
            self._cycles.popitem(last=False)
        return n

    def _meta(self, env: Any, **more: str | int | float | bool) -> Values:
        return Values(
            {
                "uid": _hex(env.uid),
                "cycle_id": _hex(env.cycle or (env.uid if env.uid in self._cycles else None)),
                "cause_id": _hex(env.cause),
                "source": env.source,
                "type": env.type,
                **more,
            }
        )

    def _sim_of(self, env: Any) -> int | None:
        cid = env.cycle or env.uid
        hit = self._cycle_robot.get(cid)
        return hit[2] if hit is not None else None

    @staticmethod
    def _robot(topic: str) -> str:
        head, _, _ = topic.rpartition("/")
        return head or "robot"

    # -- data -----------------------------------------------------------------------------
    def _data(self, topic: str, env: Any, body: Any, cycle: int | None) -> list[Log]:
        from rap_schemas import LaserScan, Odometry, Pose2D, SimTime, SpinPlan

        if isinstance(body, LaserScan):
            robot = self._robot(topic)
            out = []
            old = self._pending.pop(robot, None)
            if old is not None:
                out.extend(self._emit_scan(old, self._poses.get(robot)))
            self._pending[robot] = _PendingScan(env, body, robot)
            # the cycle's robot and sim time are known now: its events may come before
            # the scan is drawn (it waits for its pose)
            self._remember(env.uid, robot, None, _sim_stamp(body.stamp))
            return out
        if isinstance(body, Odometry | Pose2D):
            pose = body.pose if isinstance(body, Odometry) else body
            stamp = body.stamp if isinstance(body, Odometry) else None
            return self._pose(self._robot(topic), env, pose, stamp, cycle)
        if isinstance(body, SpinPlan):
            return self._plan(self._robot(topic), env, body, cycle)
        if isinstance(body, SimTime):
            return [
                Log(
                    ("data", *topic.split("/")),
                    (Scalar(body.t / 1e9),),
                    ts=env.ts,
                    cycle=cycle,
                    sim_ns=body.t,
                )
            ]
        return [
            Log(
                ("data", *topic.split("/")),
                (Text(_clip(f"{env.type} from {env.source}: {_summary(body)}")), self._meta(env)),
                ts=env.ts,
                cycle=cycle,
                sim_ns=self._sim_of(env),
            )
        ]

    def _pose(
        self, robot: str, env: Any, pose: Any, stamp: int | None, cycle: int | None
    ) -> list[Log]:
        import numpy as np

        p = _Pose(pose.x, pose.y, pose.theta)
        self._poses[robot] = p
        out: list[Log] = []
        pending = self._pending.get(robot)
        if pending is not None and (env.cycle == pending.env.uid or env.cycle is None):
            del self._pending[robot]
            out.extend(self._emit_scan(pending, p))
        sim = _sim_stamp(stamp) if stamp is not None else self._sim_of(env)
        path = self._paths.setdefault(robot, [])
        path.append((p.x, p.y))
        if len(path) > PATH_POINTS:
            del path[: len(path) - PATH_POINTS]
        base = ("world", robot)
        radius = self._radius(robot)
        out += [
            Log(
                (*base, "pose"),
                (Points(np.array([(p.x, p.y)], dtype=np.float64), radius), self._meta(env)),
                ts=env.ts,
                cycle=cycle,
                sim_ns=sim,
            ),
            Log(
                (*base, "heading"),
                (Arrows([(p.x, p.y)], [(0.4 * math.cos(p.theta), 0.4 * math.sin(p.theta))]),),
                ts=env.ts,
                cycle=cycle,
                sim_ns=sim,
            ),
            Log((*base, "path"), (Strips([list(path)]),), ts=env.ts, cycle=cycle, sim_ns=sim),
        ]
        return out

    def _radius(self, robot: str) -> float:
        if self.world is not None:
            for r in self.world.robots:
                if r.name == robot:
                    return float(r.radius)
        return ROBOT_RADIUS

    def _remember(self, cid: bytes, robot: str, pose: _Pose | None, stamp: int | None) -> None:
        self._cycle_robot[cid] = (robot, pose, stamp)
        if len(self._cycle_robot) > 4096:
            self._cycle_robot.popitem(last=False)

    def _emit_scan(self, pending: _PendingScan, pose: _Pose | None) -> list[Log]:
        import numpy as np

        env, scan, robot = pending.env, pending.scan, pending.robot
        p = pose or _Pose(0.0, 0.0, 0.0)
        cycle = self._cycles.get(env.uid)
        stamp = _sim_stamp(scan.stamp)
        self._remember(env.uid, robot, pose, stamp)
        ranges = np.frombuffer(scan.ranges, "<f4").astype(np.float64)
        angles = p.theta + scan.angle_min + scan.angle_increment * np.arange(ranges.size)
        hit = np.isfinite(ranges)
        pts = np.column_stack(
            [p.x + ranges[hit] * np.cos(angles[hit]), p.y + ranges[hit] * np.sin(angles[hit])]
        )
        meta = self._meta(
            env, beams=int(ranges.size), returns=int(hit.sum()), pose_known=pose is not None
        )
        return [
            Log(
                ("world", robot, "scan"),
                (Points(pts, 0.02, SCAN_GREEN), meta),
                ts=env.ts,
                cycle=cycle,
                sim_ns=stamp,
            )
        ]

    def _plan(self, robot: str, env: Any, plan: Any, cycle: int | None) -> list[Log]:
        sim = self._sim_of(env)
        out = [
            Log(
                ("world", robot, "plans"),
                (Text(_plan_text(plan)), self._meta(env)),
                ts=env.ts,
                cycle=cycle,
                sim_ns=sim,
            )
        ]
        if cycle is not None:
            out.append(
                Log(
                    ("maplek", robot, "cycles"),
                    (Text(f"cycle #{cycle}: plan at the robot"), self._meta(env)),
                    ts=env.ts,
                    cycle=cycle,
                    sim_ns=sim,
                )
            )
        return out

    # -- events, traces, trust, logs ----------------------------------------------------
    def _event(self, name: str, env: Any, body: Any, cycle: int | None) -> list[Log]:
        import numpy as np
        from rap_schemas import Empty, LidarMask, PlanProposal, Verdict

        level = "INFO"
        if isinstance(body, LidarMask):
            flags = np.frombuffer(body.occluded, np.uint8).astype(bool)
            what = f"{int(flags.sum())} of {flags.size} beams flagged"
        elif isinstance(body, PlanProposal):
            what = f"plan {_short(body.plan_uid)} by {body.proposer}: {_proposal_text(body)}"
        elif isinstance(body, Verdict):
            verdict = "approved" if body.approved else "rejected"
            what = f"plan {_short(body.plan_uid)} {verdict} by {body.legitimator}"
            if body.reason:
                what += f": {body.reason}"
            if not body.approved:
                level = "WARN"
        elif isinstance(body, Empty):
            what = ""
        else:
            what = f"{env.type} {_summary(body)}"
        sim = self._sim_of(env)
        number = "-" if cycle is None else f"#{cycle}"
        text = f"{name}: {what} " if what else f"{name} "
        text += f"(cycle {number}, cause {_short(env.cause)}, from {env.source})"
        out = [
            Log(
                ("maplek", "events", *name.split("/")),
                (Text(_clip(text), level), self._meta(env)),
                ts=env.ts,
                cycle=cycle,
                sim_ns=sim,
            )
        ]
        if isinstance(body, LidarMask) and name == "anomaly":  # not a scan's plain mask
            out.extend(self._mask(env, body, cycle, sim))
        return out

    def _mask(self, env: Any, mask: Any, cycle: int | None, sim: int | None) -> list[Log]:
        import numpy as np

        hit = self._cycle_robot.get(env.cycle or b"")
        if hit is not None:
            robot, pose = hit[0], hit[1] or self._poses.get(hit[0])
        elif len(self._poses) == 1:
            robot, pose = next(iter(self._poses.items()))
        else:
            return []
        p = pose or _Pose(0.0, 0.0, 0.0)
        flags = np.frombuffer(mask.occluded, np.uint8).astype(bool)
        angles = p.theta + mask.angle_min + mask.angle_increment * np.arange(flags.size)
        pts = np.column_stack(
            [
                p.x + OCCLUDED_MARK * np.cos(angles[flags]),
                p.y + OCCLUDED_MARK * np.sin(angles[flags]),
            ]
        )
        return [
            Log(
                ("world", robot, "anomaly"),
                (Points(pts, 0.03, FLAG_RED), self._meta(env)),
                ts=env.ts,
                cycle=cycle,
                sim_ns=sim,
            )
        ]

    def _trace(self, env: Any, rec: Any, cycle: int | None) -> list[Log]:
        from rap_schemas import StageTrace

        if not isinstance(rec, StageTrace):
            return self._other(("maplek", "trace"), env, rec, cycle)
        if not rec.ended:
            return []  # its end record says it all
        n = self._cycles.get(rec.cycle) if rec.cycle else None
        if n is None and rec.cycle:
            n = self._new_cycle(rec.cycle)
        sent = ", ".join(k.rsplit("/", 1)[-1] for k in rec.sent)
        text = (
            f"cycle #{n}: {rec.node}.{rec.handler} {rec.duration_ns / 1000:.0f} us"
            + (f" sent {sent}" if sent else "")
            + ("" if rec.ok else f" FAILED: {rec.error}")
        )
        where = (
            ("maplek", rec.stage.value) if rec.stage is not None else ("maplek", "nodes", rec.node)
        )
        hit = self._cycle_robot.get(rec.cycle)
        return [
            Log(
                where,
                (
                    Text(_clip(text), "INFO" if rec.ok else "ERROR"),
                    Values(
                        {
                            "uid": _hex(env.uid),
                            "cycle_id": _hex(rec.cycle),
                            "cause_id": _hex(rec.trigger),
                            "trigger_key": rec.trigger_key,
                            "node": rec.node,
                            "handler": rec.handler,
                            "duration_ns": int(rec.duration_ns),
                        }
                    ),
                ),
                ts=env.ts,
                cycle=n,
                sim_ns=hit[2] if hit is not None else None,
            )
        ]

    def _trust(self, name: str, env: Any, body: Any, cycle: int | None) -> list[Log]:
        from rap_schemas import TrustOutput, TrustVerdict

        entity = ("trust", *name.split("/"))
        if isinstance(body, TrustOutput):
            v = body.value
            if isinstance(v, bool | int | float) and not body.deferred and math.isfinite(v):
                return [Log(entity, (Scalar(float(v)),), ts=env.ts, cycle=cycle)]
            shown = "deferred" if body.deferred else _summary(v)
            return [
                Log(entity, (Text(_clip(f"tick {body.tick}: {shown}")),), ts=env.ts, cycle=cycle)
            ]
        if isinstance(body, TrustVerdict):
            level = {"critical": "CRITICAL", "error": "ERROR", "info": "INFO"}.get(
                body.severity or "", "WARN"
            )
            why = "; ".join(f"{c.expr} = {_summary(c.value)}" for c in body.because[:4])
            text = f"{body.kind} {body.stream} at tick {body.tick}: {body.message or body.expr}"
            text += f" (because {why})" if why else ""
            return [Log(entity, (Text(_clip(text), level),), ts=env.ts, cycle=cycle)]
        return self._other(entity, env, body, cycle)

    def _log(self, node: str, env: Any, body: Any, cycle: int | None) -> list[Log]:
        from rap_schemas import Rejection

        if isinstance(body, Rejection):
            text = f"{body.node} refused {body.count} sample(s) on {body.key}: {body.reason}"
            return [Log(("log", node), (Text(_clip(text), "WARN"),), ts=env.ts, cycle=cycle)]
        return self._other(("log", node), env, body, cycle)

    def _other(self, entity: tuple[str, ...], env: Any, body: Any, cycle: int | None) -> list[Log]:
        text = _clip(f"{env.type} from {env.source}: {_summary(body)}")
        return [Log(entity, (Text(text), self._meta(env)), ts=env.ts, cycle=cycle)]


def _sim_stamp(stamp: int) -> int | None:
    """A sensor stamp as sim time, when it is a simulator's clock (not UTC)."""
    return stamp if stamp < SIM_STAMP_LIMIT else None


def _summary(value: Any) -> str:
    """A short text of a decoded body (bounded: never renders a huge value whole)."""
    if isinstance(value, msgspec.Struct):
        parts = []
        for f in value.__struct_fields__[:8]:
            v = getattr(value, f)
            parts.append(f"{f}={_summary(v)}")
        return "{" + ", ".join(parts) + "}"
    if isinstance(value, bytes | bytearray):
        return f"<{len(value)} bytes>"
    if isinstance(value, list | tuple):
        return f"[{len(value)} items]" if len(value) > 4 else repr(list(value))[:TEXT_CHARS]
    if isinstance(value, dict):
        return f"{{{len(value)} keys}}" if len(value) > 6 else repr(value)[:TEXT_CHARS]
    return repr(value)[:80]


def _plan_text(plan: Any) -> str:
    """A spin plan as the demo's recording writes it."""
    text = ", ".join(f"{c.omega:+.2f} rad/s for {c.duration:.2f} s" for c in plan.commands)
    return f"plan every {plan.period:g} s: {text or 'nominal'}"


def _proposal_text(proposal: Any) -> str:
    from rap_schemas import SpinPlan

    if proposal.plan_type == SpinPlan.TYPE:
        try:
            return _plan_text(msgspec.convert(proposal.plan, SpinPlan))
        except msgspec.ValidationError as exc:
            return f"{proposal.plan_type} that does not fit its type ({exc})"
    return f"{proposal.plan_type} {_summary(proposal.plan)}"


# -- the Rerun side --------------------------------------------------------------------


class Writer:
    """Logs :class:`Log` batches to a Rerun recording on a thread of its own, fed by a
    bounded queue (the event loop never waits on Rerun: a batch that finds the queue
    full is dropped and counted)."""

    def __init__(self, rec: rr_mod.RecordingStream, capacity: int = QUEUE_BATCHES) -> None:
        import rerun as rr

        self.rr = rr
        self.rec = rec
        self.dropped = 0
        self.logged = 0
        self.failed: Counter[str] = Counter()
        self._queue: queue.Queue[list[Log] | None] = queue.Queue(capacity)
        self._thread = threading.Thread(target=self._run, name="rap-view-rerun", daemon=True)
        self._thread.start()

    def offer(self, batch: list[Log]) -> bool:
        """Queue a batch without waiting; False (and counted) when the queue is full."""
        if not batch:
            return True
        try:
            self._queue.put_nowait(batch)
        except queue.Full:
            self.dropped += 1
            return False
        return True

    def _run(self) -> None:
        while True:
            batch = self._queue.get()
            if batch is None:
                return
            for op in batch:
                try:
                    self._log(op)
                except (ValueError, TypeError, RuntimeError) as exc:  # Rerun refused it
                    self.failed[f"{'/'.join(op.entity)}: {type(exc).__name__}: {exc}"[:160]] += 1
                else:
                    self.logged += 1

    def _log(self, op: Log) -> None:
        import numpy as np

        rr, rec = self.rr, self.rec
        if not op.static:
            rec.reset_time()
            if op.ts is not None:
                rec.set_time("time", timestamp=np.datetime64(op.ts, "ns"))
            if op.cycle is not None:
                rec.set_time("cycle", sequence=op.cycle)
            if op.sim_ns is not None:
                rec.set_time("sim", duration=np.timedelta64(op.sim_ns, "ns"))
        archetypes = [self._archetype(v) for v in op.items]
        rec.log(rr.new_entity_path(list(op.entity)), *archetypes, static=op.static)

    def _archetype(self, v: Visual) -> Any:
        rr = self.rr
        if isinstance(v, Points):
            return rr.Points2D(v.positions, radii=v.radius, colors=v.color)
        if isinstance(v, Arrows):
            return rr.Arrows2D(origins=v.origins, vectors=v.vectors)
        if isinstance(v, Strips):
            return rr.LineStrips2D(v.strips)
        if isinstance(v, Text):
            return rr.TextLog(v.text, level=v.level)
        if isinstance(v, Scalar):
            return rr.Scalars(v.value)
        return rr.AnyValues(**v.values)

    def close(self, timeout: float = 30.0) -> str | None:
        """Log what is queued, then flush and end the recording (blocking: run it on a
        thread). None when done, else what went wrong."""
        deadline = time.monotonic() + timeout
        try:
            self._queue.put(None, timeout=timeout)
        except queue.Full:
            return f"Rerun took no data for {timeout:g} s"
        self._thread.join(max(0.0, deadline - time.monotonic()))
        if self._thread.is_alive():
            return f"Rerun took no data for {timeout:g} s"
        try:
            self.rec.flush(timeout_sec=max(0.1, deadline - time.monotonic()))
        except (RuntimeError, ValueError) as exc:
            return f"Rerun could not flush it: {exc}"
        finally:
            self.rec.disconnect()
        return None


def _blueprint() -> Any:
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(name="world", origin="/world"),
            rrb.Vertical(
                rrb.TextLogView(name="MAPLE-K", origin="/maplek"),
                rrb.TimeSeriesView(name="trust", origin="/trust"),
                rrb.TextLogView(name="rejections", origin="/log"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=False,
    )


def _viewer_executable() -> str | None:
    """The Rerun viewer program (``rerun``: on PATH, or beside this Python)."""
    found = shutil.which("rerun")
    if found:
        return found
    here = Path(sys.executable).with_name("rerun.exe" if os.name == "nt" else "rerun")
    return str(here) if here.is_file() else None


def _has_display() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


HOW_ELSE = (
    "give --save FILE.rrd (open it later with `rerun FILE.rrd`) or --connect-viewer URL "
    "of a viewer that runs elsewhere (rerun+http://HOST:9876/proxy)"
)


def _open_recording(
    system: str, spawn: bool, viewer_url: str | None, save: Path | None
) -> tuple[rr_mod.RecordingStream, str]:
    """The recording and where it goes (said to the user); a usage error otherwise."""
    import rerun as rr

    rec = rr.RecordingStream("rap_view", recording_id=f"rap_view-{system}-{time.time_ns()}")
    blueprint = _blueprint()
    if save is not None:
        try:
            rec.save(save, default_blueprint=blueprint)
        except (RuntimeError, OSError) as exc:
            usage(f"--save {save}: cannot write the recording ({exc}) - give a writable file path")
        return rec, f"the file {save}"
    if viewer_url is not None:
        try:
            rec.connect_grpc(viewer_url, default_blueprint=blueprint)
        except (RuntimeError, ValueError) as exc:
            usage(
                f"--connect-viewer {viewer_url}: {exc} - give the viewer's URL, e.g. "
                "rerun+http://127.0.0.1:9876/proxy"
            )
        return rec, f"the viewer at {viewer_url}"
    exe = _check_spawn()
    try:
        rr.spawn(
            executable_path=exe,
            recording=rec,
            default_blueprint=blueprint,
            hide_welcome_screen=True,
        )
    except (RuntimeError, OSError) as exc:
        failed(f"could not spawn a Rerun viewer ({exc}) - {HOW_ELSE}")
    return rec, "a spawned Rerun viewer" if spawn else "a spawned Rerun viewer (default)"


def _check_spawn() -> str:
    """The viewer program to spawn; a usage error when none can be spawned here."""
    exe = _viewer_executable()
    if exe is None or not _has_display():
        why = "no Rerun viewer program (rerun) is installed" if exe is None else "no display"
        usage(f"cannot spawn a Rerun viewer here ({why}) - {HOW_ELSE}")
    return exe


def _check_save(path: Path) -> None:
    if path.is_dir():
        usage(f"--save {path}: is a directory - give a file path, e.g. {path / 'view.rrd'}")
    if not path.parent.is_dir():
        usage(f"--save {path}: the directory {path.parent} does not exist - create it first")


def _check_url(url: str) -> None:
    scheme, sep, rest = url.partition("://")
    if not sep or not rest or not scheme.startswith("rerun"):
        usage(
            f"--connect-viewer {url!r} is not a Rerun viewer URL - give one like "
            "rerun+http://127.0.0.1:9876/proxy"
        )


# -- what the model tells ----------------------------------------------------------------


def cycle_keys(plan: DeploymentPlan | None) -> set[str]:
    """The data keys the model's monitors read: each of their samples starts a cycle."""
    from rap_schemas import keys

    out: set[str] = set()
    if plan is None:
        return out
    for comp in plan.components.values():
        if comp.stage != "monitor":
            continue
        for name, port in comp.ports.items():
            if port.direction != "out" and port.kind == "data":
                try:
                    out.add(keys.data(plan.system, port.topic or name))
                except keys.KeyError_:
                    continue
    return out


def model_world(plan: DeploymentPlan | None, model_dir: Path | None) -> str | None:
    """The world a simulator of the model runs (its ``run:`` command's ``--world``)."""
    if plan is None:
        return None
    for comp in plan.components.values():
        run = comp.run
        if not any("sim_world" in a for a in run) or "--world" not in run:
            continue
        i = run.index("--world")
        if i + 1 >= len(run):
            continue
        ref = run[i + 1].replace("{model_dir}", str(model_dir or "."))
        bare = "/" not in ref and "\\" not in ref and "." not in ref
        if not bare and model_dir is not None and not Path(ref).is_absolute():
            ref = str(model_dir / ref)
        return ref
    return None


def load_world_ref(ref: str) -> WorldSpec:
    from sim_world.world import find_world, load_world

    return load_world(find_world(ref))


# -- the command ----------------------------------------------------------------------------


@dataclass
class _Progress:
    translator: Translator
    writer: Writer
    inbox_dropped: int = 0
    tty: bool = field(default_factory=lambda: sys.stderr.isatty())
    _last: float = 0.0
    _said: set[str] = field(default_factory=set)

    @property
    def dropped(self) -> int:
        return self.inbox_dropped + self.writer.dropped

    def line(self) -> str:
        t, w = self.translator, self.writer
        text = f"rap view: {t.viewed} samples viewed, {self.dropped} dropped"
        rejected = sum(t.rejected.values())
        if rejected:
            text += f", {rejected} rejected"
        if w.failed:
            text += f", {sum(w.failed.values())} refused by Rerun"
        return text

    def tick(self, final: bool = False) -> None:
        for reason in list(self.translator.rejected)[:32]:
            if reason not in self._said and len(self._said) < 64:
                self._said.add(reason)
                self._say(f"rap view: rejected a sample: {reason}")
        if self.tty and not final:
            sys.stderr.write("\r" + self.line() + "\x1b[K")
            sys.stderr.flush()
        elif final or time.monotonic() - self._last >= 5.0:
            self._last = time.monotonic()
            self._say(self.line())

    def _say(self, text: str) -> None:
        if self.tty:
            sys.stderr.write("\r\x1b[K")
        sys.stderr.write(text + "\n")
        sys.stderr.flush()


class _Merged:
    """The samples of several subscriptions in the order they arrived (one consumer per
    subscription would take an event before the scan that caused it)."""

    def __init__(self, subs: list[Any]) -> None:
        import anyio

        self.subs = subs
        self._held: list[Any] = []
        self._bell = anyio.Event()

    def start(self, tg: Any) -> None:
        for sub in self.subs:
            tg.start_soon(self._wait, sub)

    async def _wait(self, sub: Any) -> None:
        async for sample in sub:
            self._held.append(sample)
            self._bell.set()

    async def next(self) -> list[Any]:
        """Every sample that has arrived, oldest first (waits for one)."""
        import anyio

        await self._bell.wait()
        self._bell = anyio.Event()
        return self.now()

    def now(self) -> list[Any]:
        """Every sample that has arrived, oldest first (none: an empty list)."""
        batch, self._held = self._held, []
        for sub in self.subs:
            while (sample := sub.get_nowait()) is not None:
                batch.append(sample)
        batch.sort(key=lambda s: s.arrived)
        return batch


_KINDS: Final = ("data", "event", "trace", "trust", "log")


async def _view(
    reach: Reach,
    translator: Translator,
    open_sink: Callable[[], tuple[rr_mod.RecordingStream, str]],
    duration: float | None,
) -> tuple[_Progress, str | None, str]:
    """Follow the system until SIGINT/SIGTERM or ``duration``; the progress, whether the
    recording was finished, and where it went. Signals are taken from the start to the
    end: a second Ctrl-C while the recording is finished does not cut it short."""
    import anyio

    stop = anyio.CancelScope()

    async def on_signals(signals: Any) -> None:
        async for _ in signals:
            if not stop.cancel_called:
                stop.cancel()
            else:
                sys.stderr.write("rap view: finishing the recording, one moment\n")
                sys.stderr.flush()

    with anyio.open_signal_receiver(signal.SIGINT, signal.SIGTERM) as signals:
        async with anyio.create_task_group() as tg:
            tg.start_soon(on_signals, signals)
            try:
                result = await _follow(reach, translator, open_sink, duration, stop)
            finally:
                tg.cancel_scope.cancel()
    return result


async def _follow(
    reach: Reach,
    translator: Translator,
    open_sink: Callable[[], tuple[rr_mod.RecordingStream, str]],
    duration: float | None,
    stop: Any,
) -> tuple[_Progress, str | None, str]:
    import anyio
    from rap_schemas import keys
    from rap_sdk import InboxPolicy, Overflow

    policy = InboxPolicy(
        capacity=INBOX_SAMPLES, overflow=Overflow.FIFO, block=False, max_bytes=INBOX_BYTES
    )
    async with open_fabric(reach) as fabric:
        # the fabric first: no recording is made for a system that cannot be reached
        rec, sink = await anyio.to_thread.run_sync(open_sink)
        writer = Writer(rec)
        progress = _Progress(translator, writer)
        writer.offer(translator.static())
        subs = [fabric.subscribe(keys.pattern(reach.system, keys.Kind(k)), policy) for k in _KINDS]
        merged = _Merged(subs)

        async def consume() -> None:
            while True:
                # a batch is what the inboxes held (bounded): taken whole, no await inside
                for sample in await merged.next():
                    writer.offer(translator.take(sample.key, sample.payload))

        async def report() -> None:
            while True:
                await anyio.sleep(1.0)
                progress.inbox_dropped = sum(s.stats.dropped for s in subs)
                progress.tick()

        sys.stderr.write(
            f"rap view: viewing system {reach.system} through {reach.where} in {sink}; "
            "Ctrl-C to stop\n"
        )
        sys.stderr.flush()
        try:
            with stop:
                async with anyio.create_task_group() as tg:
                    tg.start_soon(report)
                    merged.start(tg)
                    tg.start_soon(consume)
                    if duration is not None:
                        await anyio.sleep(duration)
                        tg.cancel_scope.cancel()
            # what is in flight still counts: take samples until none came for a moment
            with anyio.move_on_after(DRAIN_MAX):
                quiet = 0.0
                while quiet < DRAIN_QUIET:
                    batch = merged.now()
                    for sample in batch:
                        writer.offer(translator.take(sample.key, sample.payload))
                    quiet = 0.0 if batch else quiet + 0.05
                    await anyio.sleep(0.05)
        finally:
            progress.inbox_dropped = sum(s.stats.dropped for s in subs)
            for sub in subs:
                sub.close()
            with anyio.CancelScope(shield=True):
                writer.offer(translator.flush())
                closed = await anyio.to_thread.run_sync(writer.close)
    return progress, closed, sink


@reach_options
def view(
    spawn: Annotated[
        bool, typer.Option("--spawn", help="Spawn a Rerun viewer and stream to it (the default).")
    ] = False,
    connect_viewer: Annotated[
        str | None,
        typer.Option(
            "--connect-viewer",
            help="Stream to a running Rerun viewer at this URL (rerun+http://HOST:9876/proxy).",
            show_default=False,
        ),
    ] = None,
    save: Annotated[
        Path | None,
        typer.Option(
            "--save",
            help="Write a Rerun recording (.rrd) instead; closed on Ctrl-C.",
            show_default=False,
        ),
    ] = None,
    world: Annotated[
        str | None,
        typer.Option(
            "--world",
            help="Draw this world (a shipped world's name or a world file); default: the "
            "world the model's simulator runs (its run: command's --world).",
            show_default=False,
        ),
    ] = None,
    duration: Annotated[
        float | None,
        typer.Option(
            "--duration",
            help="Stop after this many seconds (default: at Ctrl-C).",
            show_default=False,
        ),
    ] = None,
    *,
    where: Where,
) -> None:
    """Show a running system live in Rerun: the world, the robot's pose and path, its
    scans, the anomalies, plans and verdicts of each MAPLE-K cycle (every entity carries
    its uid, cycle and cause, and the `cycle` timeline numbers the cycles), trust outputs
    and rejected samples. With no option it spawns a viewer; `--save` writes an `.rrd`
    file (flushed on Ctrl-C), `--connect-viewer` streams to a viewer elsewhere. A
    progress line on stderr counts the samples viewed, dropped and rejected.

    Example, with the lidar case running (`rap up examples/lidar_occlusion/model.yaml
    --all`):

        rap view -m examples/lidar_occlusion/model.yaml --save view.rrd

    then Ctrl-C, and `rerun view.rrd`. Exit 0 when stopped, 1 when the fabric cannot be
    reached or the recording could not be finished, 2 for bad usage."""
    chosen = [
        n
        for n, v in (("--spawn", spawn), ("--connect-viewer", connect_viewer), ("--save", save))
        if v
    ]
    if len(chosen) > 1:
        usage(f"give one of --spawn, --connect-viewer, --save (got {' and '.join(chosen)})")
    if duration is not None and not (0 < duration <= 7 * 86_400):
        usage(f"--duration {duration:g}: give seconds, 0 < s <= 604800")
    if save is not None:
        _check_save(save)
    if connect_viewer is not None:
        _check_url(connect_viewer)
    reach = where.resolve()
    spec = _world(world, where.model, reach)
    if save is None and connect_viewer is None:
        _check_spawn()
    translator = Translator(reach.system, cycle_keys(reach.plan), spec)
    import anyio
    from rap_sdk.entry import leaf

    try:
        progress, closed, sink = anyio.run(
            _view,
            reach,
            translator,
            functools.partial(_open_recording, reach.system, spawn, connect_viewer, save),
            duration,
        )
    except BaseExceptionGroup as group:  # a task group's wrapping of typer.Exit
        raise leaf(group) from None
    progress.tick(final=True)
    for reason, n in translator.rejected.most_common(5):
        sys.stderr.write(f"  rejected {n}x: {reason}\n")
    for reason, n in progress.writer.failed.most_common(5):
        sys.stderr.write(f"  refused by Rerun {n}x: {reason}\n")
    if closed is not None:
        failed(
            f"the recording in {sink} is not complete: {closed} - is the viewer still "
            "running there? (--save FILE.rrd writes a file instead)"
            if connect_viewer is not None
            else f"the recording in {sink} is not complete: {closed}"
        )
    if save is not None:
        sys.stderr.write(f"rap view: wrote {save} - open it with `rerun {save}`\n")


def _world(ref: str | None, model: Path | None, reach: Reach) -> WorldSpec | None:
    from sim_world.world import WorldError

    from .reach import find_model

    if ref is not None:
        try:
            return load_world_ref(ref)
        except WorldError as exc:
            usage(f"--world {exc}")
    file = find_model(model)
    found = model_world(reach.plan, file.parent if file is not None else None)
    if found is None:
        return None
    try:
        return load_world_ref(found)
    except WorldError as exc:
        sys.stderr.write(f"rap view: not drawing the model's world: {exc}\n")
        return None


def register(app: typer.Typer) -> None:
    """Add ``rap view`` to ``app``."""
    app.command("view")(view)
