"""Which lidar beams an occlusion schedule covers at a time (ground truth).

Beam angles are in the robot's frame. A beam at angle ``a`` is inside an arc
(``start``, ``width``) when ``(a - start) mod 2pi < width``. ``random`` occlusions draw
1 to 3 arcs of 15 to 90 degrees per ``period``, from a generator seeded by the world's
seed, the occlusion's index and the period number: the same world gives the same arcs.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from .world import Occlusion

__all__ = ["GLOBAL_WINDOW", "active_arcs", "occlusion_mask"]

GLOBAL_WINDOW = math.radians(60.0)
"""What a ``global`` occlusion leaves visible, centred on its ``start_angle``."""

TWO_PI = 2 * math.pi


def active_arcs(occ: Occlusion, index: int, t: float, seed: int) -> list[tuple[float, float]]:
    """The (start, width) arcs of one occlusion at time ``t`` (empty when inactive)."""
    if t < occ.t_start or (occ.t_end is not None and t >= occ.t_end):
        return []
    if occ.mode == "sector":
        return [(occ.start_angle, occ.width)]
    if occ.mode == "arcs":
        return [(a.start_angle, a.width) for a in occ.arcs]
    if occ.mode == "global":
        return [(occ.start_angle + GLOBAL_WINDOW / 2, TWO_PI - GLOBAL_WINDOW)]
    epoch = int((t - occ.t_start) // occ.period)
    rng = np.random.default_rng([seed, index, epoch])
    n = int(rng.integers(1, 4))
    return [
        (
            float(rng.uniform(-math.pi, math.pi)),
            float(rng.uniform(math.radians(15), math.radians(90))),
        )
        for _ in range(n)
    ]


def occlusion_mask(
    occlusions: list[Occlusion], robot: str, t: float, angles: npt.NDArray[np.float64], seed: int
) -> npt.NDArray[np.bool_]:
    """True for each beam (robot-frame ``angles``) covered at time ``t``."""
    mask = np.zeros(angles.shape[0], dtype=bool)
    for i, occ in enumerate(occlusions):
        if occ.robot != robot:
            continue
        for start, width in active_arcs(occ, i, t, seed):
            mask |= np.mod(angles - start, TWO_PI) < width
    return mask
