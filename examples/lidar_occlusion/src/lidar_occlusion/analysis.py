"""Telling occlusion from obstacles: the reference analysis as pure functions.

Frame convention (explicit, where RPIO silently rotated by -pi/2 for the TB4 mount):
beam ``i`` points at ``angle_min + i * angle_increment`` radians in the robot's base
frame, x forward, counter-clockwise positive; :func:`signed_angles` maps them into
(-pi, pi]. A publisher whose lidar is mounted rotated corrects that before publishing
(sim_world publishes in ``<robot>/base_link``).

1. :func:`raw_mask`: a beam is occluded when it has no finite return.
2. :class:`MaskWindow`: the mean of the last ``window`` masks is a probability per beam;
   above ``threshold`` counts as occluded.
3. :func:`clean`: morphological opening, then closing, with a structuring element of
   +-``radius`` rad (circular: beam 0 neighbours the last beam), which drops specks
   narrower than the element and fills gaps narrower than it.
4. The band behind the robot, ``|angle| > ignore_from`` (the reference's (3pi/4, 5pi/4)
   in [0, 2pi)), never counts: the robot's own body sits there on a TB4.
5. :func:`is_anomaly`: the cleaned mask differs from the last planned one by more than
   ``min_arc`` rad of arc, and no anomaly is being handled.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Annotated

import msgspec
import numpy as np
import numpy.typing as npt
from rap_schemas import LaserScan, LidarMask, pack_flags

__all__ = [
    "AnalysisConfig",
    "MaskWindow",
    "analyse_scan",
    "clean",
    "differing_arc",
    "ignore_band",
    "is_anomaly",
    "raw_mask",
    "signed_angles",
    "to_message",
]

Mask = npt.NDArray[np.bool_]


class AnalysisConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    window: Annotated[int, msgspec.Meta(ge=1, le=10_000)] = 3
    """Scans the occlusion probability is taken over."""
    threshold: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)] = 0.3
    """A beam whose probability of no return is above this counts as occluded."""
    radius: float = math.pi / 48
    """Half-width of the opening/closing element, rad (3.75 degrees)."""
    ignore_from: float = 3 * math.pi / 4
    """Beams with ``|angle| >`` this are behind the robot and ignored."""
    min_arc: float = math.pi / 48
    """An anomaly needs more than this arc (rad) of change against the planned mask."""
    handling_timeout: float = 0.6
    """Seconds of scan time after which an anomaly still marked as being handled is
    given up on and may be raised again. A healthy cycle resolves it within one scan;
    past the gate's plan age (0.2 s) its plan can no longer run, so it was lost: a stage
    that died mid-cycle, or a plan sent to a stage that was not there. A restarted stage
    therefore gets the next anomaly at most this long after the last one."""


def signed_angles(angle_min: float, angle_increment: float, n: int) -> npt.NDArray[np.float64]:
    """Each beam's angle in (-pi, pi]."""
    a = angle_min + np.arange(n, dtype=np.float64) * angle_increment
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


def raw_mask(ranges: npt.ArrayLike) -> Mask:
    """True where a beam has no finite return (``inf`` or ``nan``). ``ranges`` may be a
    float array of any precision (``LaserScan.values()`` is float32, read in place)."""
    values = np.asarray(ranges)
    if values.dtype.kind != "f":
        values = values.astype(np.float64)
    mask: Mask = ~np.isfinite(values)
    return mask


def _shifts(mask: Mask, k: int, *, any_: bool) -> Mask:
    out = mask.copy()
    for s in range(1, k + 1):
        for rolled in (np.roll(mask, s), np.roll(mask, -s)):
            if any_:
                out |= rolled
            else:
                out &= rolled
    return out


def clean(mask: Mask, k: int) -> Mask:
    """Opening then closing with a circular element of ``2k + 1`` beams."""
    if k <= 0 or mask.size == 0:
        return mask.copy()
    if k * 2 + 1 >= mask.size:
        return np.full_like(mask, bool(mask.all()))
    opened = _shifts(_shifts(mask, k, any_=False), k, any_=True)
    return _shifts(_shifts(opened, k, any_=True), k, any_=False)


def ignore_band(angles: npt.NDArray[np.float64], ignore_from: float) -> Mask:
    """True for the beams that never count (behind the robot)."""
    return np.abs(angles) > ignore_from


class MaskWindow:
    """The last ``size`` raw masks; ``probability()`` is their mean per beam."""

    def __init__(self, size: int = 3) -> None:
        self.size = size
        self.masks: deque[Mask] = deque(maxlen=size)

    def push(self, mask: Mask) -> None:
        if self.masks and self.masks[0].shape != mask.shape:
            self.masks.clear()  # the lidar changed its beam count: start over
        self.masks.append(mask)

    def probability(self) -> npt.NDArray[np.float64]:
        if not self.masks:
            return np.zeros(0)
        prob: npt.NDArray[np.float64] = np.mean(np.stack(self.masks), axis=0)
        return prob

    def state(self) -> list[list[bool]]:
        return [m.tolist() for m in self.masks]

    def restore(self, state: list[list[bool]]) -> None:
        self.masks.clear()
        for m in state[-self.size :]:
            self.push(np.asarray(m, dtype=bool))


def analyse_scan(scan: LaserScan, window: MaskWindow, cfg: AnalysisConfig) -> Mask:
    """Push ``scan``'s raw mask into ``window``; the cleaned, banded occlusion mask."""
    window.push(raw_mask(scan.values()))
    occluded = window.probability() > cfg.threshold
    k = round(cfg.radius / scan.angle_increment) if scan.angle_increment > 0 else 0
    occluded = clean(occluded, k)
    angles = signed_angles(scan.angle_min, scan.angle_increment, occluded.size)
    occluded &= ~ignore_band(angles, cfg.ignore_from)
    return occluded


def differing_arc(mask: Mask, planned: Mask | None, angle_increment: float) -> float:
    """Arc (rad) of beams where ``mask`` and ``planned`` disagree (no plan: all clear)."""
    if planned is None or planned.shape != mask.shape:
        return float(np.count_nonzero(mask)) * angle_increment
    return float(np.count_nonzero(mask != planned)) * angle_increment


def is_anomaly(
    mask: Mask,
    planned: Mask | None,
    angle_increment: float,
    handling: bool,
    cfg: AnalysisConfig,
) -> bool:
    return not handling and differing_arc(mask, planned, angle_increment) > cfg.min_arc


def to_message(mask: Mask, scan: LaserScan) -> LidarMask:
    return LidarMask(
        angle_min=scan.angle_min,
        angle_increment=scan.angle_increment,
        occluded=pack_flags(mask),
        frame_id=scan.frame_id,
    )
