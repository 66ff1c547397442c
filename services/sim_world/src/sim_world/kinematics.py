"""Differential-drive kinematics with TurtleBot 4 limits (exact unicycle integration)."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["DiffDrive", "Pose2", "wrap"]


@dataclass(frozen=True, slots=True)
class Pose2:
    x: float
    y: float
    theta: float


def wrap(angle: float) -> float:
    """To (-pi, pi]."""
    a = math.fmod(angle + math.pi, 2 * math.pi)
    if a <= 0:
        a += 2 * math.pi
    return a - math.pi


@dataclass(frozen=True, slots=True)
class DiffDrive:
    wheel_separation: float = 0.233
    max_linear: float = 0.31
    max_angular: float = 1.9

    def clamp(self, v: float, w: float) -> tuple[float, float]:
        """The command limited to the robot's linear and angular speeds."""
        return (
            max(-self.max_linear, min(self.max_linear, v)),
            max(-self.max_angular, min(self.max_angular, w)),
        )

    def wheels(self, v: float, w: float) -> tuple[float, float]:
        """Left and right wheel speeds (m/s) for a body command."""
        half = self.wheel_separation / 2
        return v - w * half, v + w * half

    def step(self, pose: Pose2, v: float, w: float, dt: float) -> Pose2:
        """Move for ``dt`` s at constant (v, w), clamped: exact, arcs included."""
        v, w = self.clamp(v, w)
        th = pose.theta
        if abs(w) < 1e-9:
            return Pose2(pose.x + v * dt * math.cos(th), pose.y + v * dt * math.sin(th), th)
        r = v / w
        th2 = th + w * dt
        return Pose2(
            pose.x + r * (math.sin(th2) - math.sin(th)),
            pose.y - r * (math.cos(th2) - math.cos(th)),
            wrap(th2),
        )
