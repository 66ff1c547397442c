"""The fleet's world: ``n`` robots in one room, each driving a small square of its own."""

from __future__ import annotations

import math

from sim_world.world import Lidar, Point, Pose, RobotSpec, Room, WorldSpec

CELL = 3.0
"""Metres: each robot has a cell of its own in a grid; its route is a square inside it."""
HALF = 0.8
"""Half the side of a robot's square route."""
PHYSICS_HZ = 50.0


def robot_names(n: int) -> list[str]:
    """``r00``, ``r01``, ... (three digits from 100 robots on)."""
    width = max(2, len(str(n - 1)))
    return [f"r{i:0{width}d}" for i in range(n)]


def fleet_world(n: int, rate_hz: float, seed: int = 7) -> WorldSpec:
    """``n`` robots in a grid of ``CELL`` m cells (about twice as wide as high), each
    looping a square route in its cell; a 360-beam lidar at ``rate_hz`` on every robot."""
    cols = max(1, math.ceil(math.sqrt(2 * n)))
    rows = math.ceil(n / cols)
    robots = []
    for i, name in enumerate(robot_names(n)):
        cx, cy = (i % cols + 0.5) * CELL, (i // cols + 0.5) * CELL
        corners = [(HALF, -HALF), (HALF, HALF), (-HALF, HALF), (-HALF, -HALF)]
        robots.append(
            RobotSpec(
                name=name,
                start=Pose(x=cx - HALF, y=cy - HALF, theta=0.0),
                route=[Point(x=cx + dx, y=cy + dy) for dx, dy in corners],
                loop_route=True,
            )
        )
    return WorldSpec(
        seed=seed,
        room=Room(width=cols * CELL, height=rows * CELL),
        robots=robots,
        lidar=Lidar(rate_hz=rate_hz, noise_std=0.005),
        physics_hz=max(PHYSICS_HZ, rate_hz),
    )
