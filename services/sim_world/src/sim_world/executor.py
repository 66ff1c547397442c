"""The spin-plan executor (docs/lidar_occlusion.md).

From the moment a plan arrives, at the start of every ``period`` seconds the robot runs
the plan's commands in order (turning at ``omega`` rad/s, not moving forward, for
``duration`` s each), then navigates nominally for the rest of the period. An empty plan
restores nominal behaviour.
"""

from __future__ import annotations

from rap_schemas import SpinPlan

__all__ = ["PlanExecutor"]


class PlanExecutor:
    def __init__(self) -> None:
        self.plan: SpinPlan | None = None
        self.since = 0.0

    def apply(self, plan: SpinPlan, t: float) -> None:
        """A new plan replaces the old one; its first period starts now."""
        self.plan = plan if plan.commands else None
        self.since = t

    def omega(self, t: float) -> float | None:
        """The turn rate the plan commands at ``t``, or None for nominal navigation."""
        plan = self.plan
        if plan is None or t < self.since:
            return None
        phase = (t - self.since) % plan.period
        for cmd in plan.commands:
            if phase < cmd.duration:
                return cmd.omega
            phase -= cmd.duration
        return None
