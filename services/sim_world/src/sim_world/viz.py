"""Rerun logging of a simulation: an explicit RecordingStream (no global state) to an
``.rrd`` file or a live viewer; off unless asked for (``--rerun out.rrd``).

Entities (timeline ``sim``, seconds of sim time):

    world/room, world/obstacles          static geometry
    world/<robot>/pose, .../heading      position and heading
    world/<robot>/path                   where it has driven
    world/<robot>/scan                   lidar returns (world frame)
    world/<robot>/occluded               occluded beams, marked red near the robot
    world/<robot>/plans                  plans received (text log)
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from rap_schemas import SpinPlan

from .sim import ScanEvent, Simulation
from .world import Box, Circle, WorldSpec

__all__ = ["RerunFileError", "RerunLog"]

OCCLUDED_MARK = 0.35
"""Metres from the robot where an occluded beam is drawn."""


class RerunFileError(ValueError):
    """The recording file cannot be written; the message names it and says what to do."""


class RerunLog:
    def __init__(
        self,
        world: WorldSpec,
        *,
        path: str | None = None,
        spawn: bool = False,
        application_id: str = "rap_sim_world",
    ) -> None:
        import rerun as rr  # heavy: loaded only when Rerun logging is asked for

        self.rr = rr
        self.rec = rr.RecordingStream(application_id, recording_id=f"{application_id}-{world.seed}")
        if path is not None:
            try:
                self.rec.save(path)
            except RuntimeError as exc:  # rerun's own error for a file it cannot create
                raise RerunFileError(
                    f"{path}: cannot write the Rerun recording ({exc}) - give a file path "
                    "in an existing, writable directory"
                ) from None
        elif spawn:
            self.rec.spawn()
        self._paths: dict[str, list[tuple[float, float]]] = {}
        self._static(world)

    def _static(self, world: WorldSpec) -> None:
        rr, rec = self.rr, self.rec
        w, h = world.room.width, world.room.height
        rec.log(
            "world/room", rr.LineStrips2D([[(0, 0), (w, 0), (w, h), (0, h), (0, 0)]]), static=True
        )
        circles = [o for o in world.obstacles if isinstance(o, Circle)]
        if circles:
            rec.log(
                "world/obstacles/circles",
                rr.Points2D([(c.x, c.y) for c in circles], radii=[c.r for c in circles]),
                static=True,
            )
        boxes = [o for o in world.obstacles if isinstance(o, Box)]
        if boxes:
            rec.log(
                "world/obstacles/boxes",
                rr.LineStrips2D([[*b.corners(), b.corners()[0]] for b in boxes]),
                static=True,
            )

    def scan(self, sim: Simulation, ev: ScanEvent) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("sim", duration=ev.t)
        robot = sim.robots[ev.robot]
        pose = robot.pose
        base = f"world/{ev.robot}"
        rec.log(f"{base}/pose", rr.Points2D([(pose.x, pose.y)], radii=[robot.spec.radius]))
        rec.log(
            f"{base}/heading",
            rr.Arrows2D(
                origins=[(pose.x, pose.y)],
                vectors=[(0.4 * math.cos(pose.theta), 0.4 * math.sin(pose.theta))],
            ),
        )
        path = self._paths.setdefault(ev.robot, [])
        path.append((pose.x, pose.y))
        rec.log(f"{base}/path", rr.LineStrips2D([path]))
        angles = pose.theta + sim.beam_angles
        ranges = np.asarray(ev.scan.values())
        hit = np.isfinite(ranges)
        rec.log(
            f"{base}/scan",
            rr.Points2D(
                np.column_stack(
                    [
                        pose.x + ranges[hit] * np.cos(angles[hit]),
                        pose.y + ranges[hit] * np.sin(angles[hit]),
                    ]
                ),
                radii=0.02,
                colors=[(40, 180, 90)],
            ),
        )
        occ = ev.occluded
        rec.log(
            f"{base}/occluded",
            rr.Points2D(
                np.column_stack(
                    [
                        pose.x + OCCLUDED_MARK * np.cos(angles[occ]),
                        pose.y + OCCLUDED_MARK * np.sin(angles[occ]),
                    ]
                ),
                radii=0.03,
                colors=[(220, 40, 40)],
            ),
        )

    def plan(self, robot: str, t: float, plan: SpinPlan) -> None:
        self.rec.set_time("sim", duration=t)
        text = ", ".join(f"{c.omega:+.2f} rad/s for {c.duration:.2f} s" for c in plan.commands)
        self.rec.log(
            f"world/{robot}/plans",
            self.rr.TextLog(f"plan every {plan.period:g} s: {text or 'nominal'}"),
        )

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()

    def __enter__(self) -> RerunLog:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
