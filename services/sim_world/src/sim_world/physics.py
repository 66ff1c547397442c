"""The pymunk space of a world: static walls and obstacles (robots join it in the
simulation). Also the reference the vectorised raycaster is checked against."""

from __future__ import annotations

import math

import pymunk

from .world import Box, Circle, WorldSpec

__all__ = ["STATIC", "pymunk_ray", "static_space"]

STATIC = 1
"""The pymunk collision type of walls and obstacles."""


def static_space(world: WorldSpec) -> pymunk.Space:
    space = pymunk.Space()
    body = space.static_body
    w, h = world.room.width, world.room.height
    shapes: list[pymunk.Shape] = [
        pymunk.Segment(body, a, b, 0.0)
        for a, b in (((0, 0), (w, 0)), ((w, 0), (w, h)), ((w, h), (0, h)), ((0, h), (0, 0)))
    ]
    for ob in world.obstacles:
        if isinstance(ob, Circle):
            shapes.append(pymunk.Circle(body, ob.r, (ob.x, ob.y)))
        elif isinstance(ob, Box):
            shapes.append(pymunk.Poly(body, ob.corners()))
    for s in shapes:
        s.collision_type = STATIC
    space.add(*shapes)
    return space


def pymunk_ray(space: pymunk.Space, x: float, y: float, angle: float, range_max: float) -> float:
    """One beam by pymunk's own segment query (the reference; slow)."""
    end = (x + range_max * math.cos(angle), y + range_max * math.sin(angle))
    hit = space.segment_query_first((x, y), end, 0.0, pymunk.ShapeFilter())
    return math.inf if hit is None else hit.alpha * range_max
