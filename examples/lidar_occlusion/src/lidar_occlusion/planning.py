"""From an occlusion mask to a spin plan, and the checks a plan must pass.

Rotations (radians, counter-clockwise positive) from the occluded beams' signed angles:
with ``x = min(angles, 0)`` and ``y = max(angles, 0)``:

- nothing occluded: no rotation (the empty plan restores nominal navigation);
- nothing negative: ``[y, -y]``; nothing positive: ``[x, -x]``;
- ``y - x > pi``: a full turn, ``[2 pi]`` (it sweeps every heading and ends where it
  began: the net rotation is zero modulo 2 pi);
- otherwise both ends and back, larger magnitude first: ``[x, y - x, -y]`` when
  ``|x| >= y``, else ``[y, x - y, -x]`` (net rotation exactly zero).

Each rotation becomes ``SpinCommand(omega=+-speed, duration=|angle| / speed)``.

``PlanConfig.planner`` selects the planner: ``"reference"`` (this module) or
``"lookahead"`` (:mod:`lidar_occlusion.lookahead`: it turns only as far as it takes to
see the occluded part of the route ahead, and not at all when that was seen recently;
its settings are ``PlanConfig.lookahead``).
"""

from __future__ import annotations

import math
from typing import Literal

import msgspec
import numpy as np
import numpy.typing as npt
from rap_schemas import PlanProposal, SpinCommand, SpinPlan

from .analysis import signed_angles
from .twin import TwinConfig

__all__ = [
    "LegitimacyConfig",
    "LookaheadConfig",
    "PlanConfig",
    "check_plan",
    "commands_for",
    "plan_for",
    "rotations",
]


class LookaheadConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The ``lookahead`` planner's settings (:mod:`lidar_occlusion.lookahead`)."""

    speed: float = 1.5
    """Turn rate of every command, rad/s (within the robot's limit, 1.9 on a TB4)."""
    width: float = 0.3
    """Half-width (m) of the corridor ahead that must be seen: the robot's radius
    (0.17 m on a TB4) plus a margin."""
    near: float = 0.4
    """Metres along the route from which the corridor counts: what is nearer was
    farther away, in the corridor, a moment ago."""
    reach: float = 2.0
    """Metres along the route (past waypoints) up to which the corridor counts."""
    recent_s: float = 5.0
    """A direction seen unoccluded within this many seconds needs no spin..."""
    moved: float = 0.5
    """... if the robot was at most this many metres from where it is now when it saw
    it: the navigation remembers what it saw within 2.5 m, and ``reach + moved`` keeps
    the corridor within that."""
    edge: float = 0.05
    """Rad a direction must lie inside the visible arc to count as seen."""
    scan_period: float = 0.2
    """Seconds between scans: a sweep turns past the needed angle by half the turn
    between two scans, so that a scan catches the direction uncovered."""
    reached: float = 0.3
    """A waypoint within this many metres counts as passed (sim_world: 0.25 m)."""
    ignore_from: float = 3 * math.pi / 4
    """Beams with ``|angle| >`` this (the robot's own body) are never counted as seen."""
    bins: int = 120
    """World-frame heading bins of the record of what was seen when."""


class PlanConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    speed: float = 1.0
    """Turn rate of every command, rad/s."""
    period: float = 8.0
    replans: int = 1
    """Times a rejected plan is proposed again (freshly stamped) before giving up."""
    planner: Literal["reference", "lookahead"] = "reference"
    """``reference``: :func:`plan_for`, a spin over the whole occluded span on each
    anomaly. ``lookahead``: :func:`lidar_occlusion.lookahead.plan_lookahead`, a spin
    only over the occluded part of the route ahead, skipped when that was seen within
    ``lookahead.recent_s``; it needs the robot's pose and route and is re-decided every
    scan (:class:`lidar_occlusion.lookahead.Lookahead`)."""
    lookahead: LookaheadConfig = msgspec.field(default_factory=LookaheadConfig)
    """Settings of the ``lookahead`` planner (``period`` and ``replans`` are shared)."""
    route: list[tuple[float, float]] = msgspec.field(default_factory=list)
    """The robot's route (x, y waypoints, m, world frame), for the ``lookahead`` planner."""
    loop_route: bool = False
    """The route repeats (as a sim_world robot's with ``loop_route``)."""


def rotations(angles: npt.ArrayLike) -> list[float]:
    """The rotation sequence that looks at the occluded ``angles`` (rad, in (-pi, pi])."""
    a = np.asarray(angles, dtype=np.float64)
    if a.size == 0:
        return []
    x = min(float(a.min()), 0.0)
    y = max(float(a.max()), 0.0)
    if x == 0.0 and y == 0.0:
        return []
    if x == 0.0:
        return [y, -y]
    if y == 0.0:
        return [x, -x]
    if y - x > math.pi:
        return [2 * math.pi]
    if -x >= y:
        return [x, y - x, -y]
    return [y, x - y, -x]


def commands_for(rots: list[float], speed: float) -> list[SpinCommand]:
    return [SpinCommand(omega=math.copysign(speed, r), duration=abs(r) / speed) for r in rots]


def plan_for(
    occluded: list[bool] | npt.NDArray[np.bool_],
    angle_min: float,
    angle_increment: float,
    cfg: PlanConfig,
) -> SpinPlan:
    mask = np.asarray(occluded, dtype=bool)
    angles = signed_angles(angle_min, angle_increment, mask.size)[mask]
    return SpinPlan(commands=commands_for(rotations(angles), cfg.speed), period=cfg.period)


class LegitimacyConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    max_angular: float = 1.9
    """The robot's turn-rate limit, rad/s (a TurtleBot 4)."""
    max_age: float = 0.2
    """A plan older than this (s; one scan period at 5 Hz) is stale."""
    twin: bool = False
    """Also roll the plan out on the digital twin (:mod:`lidar_occlusion.twin`) from what
    the robot believes, and reject it on the twin's findings (a collision, too little
    clearance, a plan made for another pose or robot)."""
    route: list[tuple[float, float]] = msgspec.field(default_factory=list)
    """The robot's route (x, y waypoints, m), for the twin's nominal navigation."""
    loop_route: bool = True
    """The route repeats (the simulator's robots loop theirs)."""
    twin_config: TwinConfig = msgspec.field(default_factory=TwinConfig)
    """The twin's robot model, checks and resolution."""


def check_plan(proposal: PlanProposal[SpinPlan], now_ns: int, cfg: LegitimacyConfig) -> str | None:
    """None when the plan may run, else why not."""
    plan = proposal.plan
    if not (math.isfinite(plan.period) and plan.period > 0):
        return f"period {plan.period} s is not a positive number"
    total = 0.0
    for i, c in enumerate(plan.commands):
        if not (math.isfinite(c.omega) and math.isfinite(c.duration)) or c.duration < 0:
            return f"command {i} is not executable: omega {c.omega}, duration {c.duration}"
        if abs(c.omega) > cfg.max_angular:
            return (
                f"command {i} turns at {c.omega} rad/s, beyond the robot's limit "
                f"{cfg.max_angular} rad/s"
            )
        total += c.duration
    if plan.commands and total >= plan.period:
        return f"commands take {total:.3f} s, not within the period of {plan.period} s"
    age = (now_ns - proposal.created) / 1e9
    if age > cfg.max_age:
        return f"plan is stale: {age:.3f} s old, limit {cfg.max_age} s"
    return None
