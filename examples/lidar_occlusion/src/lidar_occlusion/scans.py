"""Synthetic scans for tests and experiments: a 360-beam ring at 3 m with one occluded
sector (beams with no return)."""

from __future__ import annotations

import math

import numpy as np
from rap_schemas import LaserScan, pack_ranges

__all__ = ["BEAMS", "occluded_scan"]

BEAMS = 360
_INC = 2 * math.pi / BEAMS
_ANGLES = -math.pi + np.arange(BEAMS) * _INC


def occluded_scan(
    start: float | None = None, width: float = 0.0, *, robot: str = "tb1", stamp: int = 0
) -> LaserScan:
    """Every beam returns 3 m, except those within ``width`` rad counter-clockwise of
    ``start`` (base frame), which return ``inf``; ``start=None``: nothing occluded."""
    r = np.full(BEAMS, 3.0)
    if start is not None:
        r[np.mod(_ANGLES - start, 2 * math.pi) < width] = np.inf
    return LaserScan(
        stamp=stamp,
        frame_id=f"{robot}/base_link",
        angle_min=-math.pi,
        angle_increment=_INC,
        range_min=0.1,
        range_max=12.0,
        ranges=pack_ranges(r),
    )
