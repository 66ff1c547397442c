"""Static scene geometry and the vectorised lidar raycaster.

The raycaster intersects every beam with every segment and circle at once in numpy
(beams x shapes arrays) instead of one pymunk query per beam; tests check it against
analytic geometry and against pymunk's own segment queries, and bench/sim measures it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from .world import Box, Circle, WorldSpec

__all__ = ["Scene", "cast_rays", "scene_of"]

F = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Scene:
    segments: F
    """(M, 4): x1, y1, x2, y2 of the walls and box edges."""
    circles: F
    """(K, 3): x, y, r of round obstacles (robots are added per scan)."""


def scene_of(world: WorldSpec) -> Scene:
    w, h = world.room.width, world.room.height
    segs = [(0.0, 0.0, w, 0.0), (w, 0.0, w, h), (w, h, 0.0, h), (0.0, h, 0.0, 0.0)]
    circles = []
    for ob in world.obstacles:
        if isinstance(ob, Circle):
            circles.append((ob.x, ob.y, ob.r))
        elif isinstance(ob, Box):
            c = ob.corners()
            segs += [(*c[i], *c[(i + 1) % 4]) for i in range(4)]
    return Scene(
        np.array(segs, dtype=np.float64).reshape(-1, 4),
        np.array(circles, dtype=np.float64).reshape(-1, 3),
    )


def cast_rays(
    x: float, y: float, angles: F, scene: Scene, range_max: float, extra_circles: F | None = None
) -> F:
    """Distance along each world-frame angle from (x, y) to the first surface, ``inf``
    where nothing is hit within ``range_max``."""
    dx, dy = np.cos(angles)[:, None], np.sin(angles)[:, None]  # (N, 1)
    best = np.full(angles.shape[0], np.inf)
    seg = scene.segments
    if seg.size:
        px, py = seg[:, 0] - x, seg[:, 1] - y  # (M,)
        ex, ey = seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]
        denom = dx * ey - dy * ex  # (N, M): cross(d, e)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # masked below
            t = (px * ey - py * ex) / denom  # along the ray
            u = (px * dy - py * dx) / denom  # along the segment
        ok = (np.abs(denom) > 1e-12) & (t >= 0) & (u >= 0) & (u <= 1)
        best = np.minimum(best, np.where(ok, t, np.inf).min(axis=1))
    circles = scene.circles if extra_circles is None else np.vstack([scene.circles, extra_circles])
    if circles.size:
        cx, cy, r = circles[:, 0] - x, circles[:, 1] - y, circles[:, 2]
        b = dx * cx + dy * cy  # (N, K): projection of the centre on the ray
        disc = b * b - (cx * cx + cy * cy - r * r)
        with np.errstate(invalid="ignore"):
            root = np.sqrt(disc)
        t1, t2 = b - root, b + root
        t = np.where(t1 >= 0, t1, t2)  # from inside a circle, the exit point
        ok = (disc > 1e-12) & (t >= 0)  # a beam that only grazes a circle passes it
        best = np.minimum(best, np.where(ok, t, np.inf).min(axis=1))
    best[best > range_max] = np.inf
    return best
