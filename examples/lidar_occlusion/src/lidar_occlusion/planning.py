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
"""

from __future__ import annotations

import math

import msgspec
import numpy as np
import numpy.typing as npt
from rap_schemas import PlanProposal, SpinCommand, SpinPlan

from .analysis import signed_angles

__all__ = [
    "LegitimacyConfig",
    "PlanConfig",
    "check_plan",
    "commands_for",
    "plan_for",
    "rotations",
]


class PlanConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    speed: float = 1.0
    """Turn rate of every command, rad/s."""
    period: float = 8.0
    replans: int = 1
    """Times a rejected plan is proposed again (freshly stamped) before giving up."""


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
