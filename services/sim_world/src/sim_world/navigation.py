"""Nominal navigation: follow the route's waypoints, steer around what the lidar sees.

The robot only knows its scan: an occluded beam reads ``inf``, which looks like free
space. That is why an unhandled occlusion leads to collisions, and why the MAPLE-K loop
that makes the robot look into the blocked sector helps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .kinematics import Pose2, wrap
from .world import RobotSpec

__all__ = ["Navigator"]

REACHED = 0.25
"""Metres from a waypoint that count as reaching it."""
SLOW, STOP = 0.55, 0.30
"""Obstacle distance ahead (m) below which the robot slows, and stops to turn away."""
FRONT = math.radians(35)


@dataclass
class Navigator:
    spec: RobotSpec
    index: int = 0
    laps: int = 0

    @property
    def done(self) -> bool:
        return not self.spec.route or (
            self.index >= len(self.spec.route) and not self.spec.loop_route
        )

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
        err = wrap(math.atan2(dy, dx) - pose.theta)
        w = 2.5 * err
        v = self.spec.max_linear * max(0.0, math.cos(err)) ** 2
        if ranges is not None:
            front = np.abs(angles) < FRONT
            ahead = float(np.min(ranges[front])) if front.any() else math.inf
            if ahead < SLOW:
                left = ranges[(angles > FRONT) & (angles < math.pi / 2)]
                right = ranges[(angles < -FRONT) & (angles > -math.pi / 2)]
                turn = 1.0 if _space(left) >= _space(right) else -1.0
                w = turn * self.spec.max_angular * 0.8
                v = 0.0 if ahead < STOP else v * (ahead - STOP) / (SLOW - STOP)
        return v, w


def _space(ranges: npt.NDArray[np.float64]) -> float:
    return float(np.mean(np.minimum(ranges, 5.0))) if ranges.size else 0.0
