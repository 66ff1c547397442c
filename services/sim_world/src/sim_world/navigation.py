"""Nominal navigation: follow the route's waypoints, steer around what the lidar sees.

The robot only knows its scan: an occluded beam reads ``inf``, which looks like free
space. That is why an unhandled occlusion leads to collisions, and why the MAPLE-K loop
that makes the robot look into the blocked sector helps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from .kinematics import Pose2, wrap
from .world import REACHED, RobotSpec

__all__ = [
    "CANDIDATES",
    "LOOKAHEAD",
    "MARGIN",
    "MEMORY_RANGE",
    "REACHED",
    "STOP",
    "Navigator",
    "fold_points",
    "near_returns",
]

F = npt.NDArray[np.float64]

LOOKAHEAD = 0.9
"""Metres ahead a heading must be clear of obstacles to be taken."""
MARGIN = 0.08
"""Clearance (m) kept beyond the robot's radius."""
STOP = 0.25
"""Free distance (m) along the chosen heading below which the robot turns in place."""
CANDIDATES = 72
"""Headings considered, evenly around the robot (5 degrees apart)."""
MEMORY_RANGE = 2.5
"""Metres within which seen obstacle points are remembered for navigation."""
_CAND = np.linspace(-math.pi, math.pi, CANDIDATES, endpoint=False)
_CAND.flags.writeable = False


def near_returns(pose: Pose2, angles: F, ranges: F, within: float = MEMORY_RANGE) -> F:
    """World-frame points, shape (K, 2), of the returns closer than ``within`` m: what
    navigation remembers of a scan taken at ``pose`` (``angles``: the beams' angles in
    the robot's frame; ``inf`` ranges are no return)."""
    world = pose.theta + angles
    near = ranges < within
    d = ranges[near]
    return np.column_stack((pose.x + d * np.cos(world[near]), pose.y + d * np.sin(world[near])))


def fold_points(pose: Pose2, ranges: F, points: F, angle_min: float, angle_increment: float) -> F:
    """``ranges`` (a scan at ``pose``, beam ``i`` at ``angle_min + i * angle_increment``
    in the robot's frame) with each world-frame point of ``points`` (K, 2) folded into
    its nearest beam, where it is nearer than that beam's return: remembered obstacles
    as navigation sees them. Returns a new array."""
    if points.size == 0:
        return ranges.copy()
    dx, dy = points[:, 0] - pose.x, points[:, 1] - pose.y
    dist = np.hypot(dx, dy)
    rel = np.mod(np.arctan2(dy, dx) - pose.theta - angle_min, 2 * np.pi)
    idx = np.rint(rel / angle_increment).astype(np.intp) % ranges.size
    out = ranges.copy()
    np.minimum.at(out, idx, dist)
    return out


@dataclass
class Navigator:
    """Go to the waypoint by the free heading closest to its direction.

    A heading is free when no lidar return lies in the corridor of the robot's width
    (plus a margin) up to ``LOOKAHEAD`` m along it. The free headings are worked out once
    per scan, in the world frame; between scans the robot steers by them."""

    spec: RobotSpec
    index: int = 0
    laps: int = 0
    _ranges: npt.NDArray[np.float64] | None = field(default=None, repr=False)
    _headings: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False)
    _free: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False)
    """Per candidate world heading: metres free along it (capped at ``LOOKAHEAD``)."""

    @property
    def done(self) -> bool:
        return not self.spec.route or (
            self.index >= len(self.spec.route) and not self.spec.loop_route
        )

    def _update(
        self, pose: Pose2, angles: npt.NDArray[np.float64], ranges: npt.NDArray[np.float64]
    ) -> None:
        self._ranges = ranges
        cand = _CAND
        hit = np.isfinite(ranges)
        r, a = ranges[hit], angles[hit]
        rel = a[None, :] - cand[:, None]
        along = r[None, :] * np.cos(rel)
        across = np.abs(r[None, :] * np.sin(rel))
        blocking = (across < self.spec.radius + MARGIN) & (along > 0) & (along < LOOKAHEAD)
        free = np.where(blocking, along, LOOKAHEAD).min(axis=1) if r.size else None
        self._free = free if free is not None else np.full(CANDIDATES, LOOKAHEAD)
        self._headings = pose.theta + cand

    def command(
        self, pose: Pose2, angles: npt.NDArray[np.float64], ranges: npt.NDArray[np.float64] | None
    ) -> tuple[float, float]:
        """(v, w) toward the current waypoint, avoiding what ``ranges`` shows."""
        route = self.spec.route
        if self.done:
            return 0.0, 0.0
        target = route[self.index % len(route)]
        dx, dy = target.x - pose.x, target.y - pose.y
        if math.hypot(dx, dy) < REACHED:
            self.index += 1
            if self.spec.loop_route and self.index % len(route) == 0:
                self.laps += 1
            return self.command(pose, angles, ranges)
        goal = math.atan2(dy, dx)
        heading, room = goal, LOOKAHEAD
        if ranges is not None:
            if ranges is not self._ranges:
                self._update(pose, angles, ranges)
            dev = np.abs(np.mod(self._headings - goal + math.pi, 2 * math.pi) - math.pi)
            open_ = self._free >= min(LOOKAHEAD, math.hypot(dx, dy))
            if open_.any():
                i = int(np.argmin(np.where(open_, dev, np.inf)))
            else:
                i = int(np.argmax(self._free - 0.01 * dev))
            heading, room = float(self._headings[i]), float(self._free[i])
        err = wrap(heading - pose.theta)
        w = 2.5 * err
        v = self.spec.max_linear * max(0.0, math.cos(err)) ** 2
        if room < STOP:
            v = 0.0
        ahead = self._free_ahead(pose)
        if ahead < LOOKAHEAD:
            v *= max(0.0, (ahead - 0.05) / LOOKAHEAD)
        return v, w

    def _free_ahead(self, pose: Pose2) -> float:
        if self._free.size == 0:
            return LOOKAHEAD
        dev = np.abs(np.mod(self._headings - pose.theta + math.pi, 2 * math.pi) - math.pi)
        return float(self._free[int(np.argmin(dev))])
