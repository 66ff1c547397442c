"""What the robot knows: a small, decaying obstacle map and the robot's belief state.

The digital twin (:mod:`lidar_occlusion.twin`) rolls plans out against this and nothing
else. Everything here is built from what the robot publishes (its scans and its
odometry pose), never from the simulator's world, and is small enough for knowledge.

:class:`ObstacleMap` keeps, in the world frame:

- obstacle cells (``cell`` m squares) where lidar returns landed, each with the time it
  last had one and the time it last had one from nearer than ``near_range`` (what the
  robot's navigation remembers: sim_world keeps the returns within 2.5 m for its
  ``obstacle_memory``); a cell without a return for ``ttl_s`` decays away, and at most
  ``max_cells`` are kept (the oldest go first);
- looked-at cells (``look_cell`` m squares): the free space a beam crossed up to its
  return (at most ``look_range`` m), with the time - "was this place seen lately?";
- looked-at directions: ``sectors`` world-frame angular sectors, each with the time a
  beam last returned along it - :meth:`ObstacleMap.seen_recently`.

An occluded beam reads ``inf``, as does a beam with nothing within range: neither adds
an obstacle nor counts as looked at (the map cannot tell them apart, so it is
conservative). Times are seconds of the robot's clock; the map stores ages (float32)
relative to its own time ``t`` and cell keys as packed integers, so a map of 2048
obstacle and 2048 looked-at cells is about 60 kB.
"""

from __future__ import annotations

import math
from typing import Annotated

import msgspec
import numpy as np
import numpy.typing as npt
from rap_schemas import LaserScan, LidarMask, Message, Odometry, Pose2D
from rap_schemas.catalog import register
from sim_world.navigation import MEMORY_RANGE

__all__ = [
    "LidarBelief",
    "MapConfig",
    "ObstacleMap",
    "belief_of",
    "update",
]

F = npt.NDArray[np.float64]
Keys = npt.NDArray[np.uint64]

_OFFSET = 1 << 31
"""Cell indices are stored offset by this, as two uint32 halves of a uint64 key."""
_KEY = np.dtype("<u8")
_AGE = np.dtype("<f4")
_NEVER = np.float32(np.inf)


class MapConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """How the map is built; a value out of range raises ``ValueError`` naming it."""

    cell: float = 0.05
    """Side of an obstacle cell, m."""
    ttl_s: float = 10.0
    """Seconds a cell (obstacle or looked-at) stays without being seen again."""
    max_cells: int = 2048
    """Obstacle cells kept at most (the oldest are dropped first)."""
    max_range: float = 4.0
    """Returns farther than this (m) are not mapped: a plan's horizon (8 s at 0.31 m/s)
    reaches about 2.5 m, and the twin's navigation looks 2.5 m ahead at most."""
    near_range: float = MEMORY_RANGE
    """A return nearer than this (m) is one the robot's navigation remembers."""
    look_cell: float = 0.25
    """Side of a looked-at cell, m."""
    look_range: float = 3.0
    """Metres along a beam (up to its return) that count as looked at."""
    max_looked: int = 2048
    """Looked-at cells kept at most."""
    sectors: int = 72
    """World-frame angular sectors of looked-at directions (72: 5 degrees each)."""

    def __post_init__(self) -> None:
        for name in ("cell", "ttl_s", "max_range", "near_range", "look_cell", "look_range"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"MapConfig.{name} = {value!r}: give a finite number > 0")
        for name, top in (("max_cells", 1 << 16), ("max_looked", 1 << 16), ("sectors", 3600)):
            value = getattr(self, name)
            if not 1 <= value <= top:
                raise ValueError(f"MapConfig.{name} = {value!r}: give a whole number 1 to {top}")


class ObstacleMap(Message, frozen=True):
    """A bounded, decaying world-frame map built by :func:`update` (see the module)."""

    TYPE = "lidar_occlusion.ObstacleMap/1"

    t: float = 0.0
    """Seconds (the robot's clock) of the last update; the ages below count from it."""
    cell: Annotated[float, msgspec.Meta(gt=0, le=100)] = 0.05
    cells: bytes = b""
    """Obstacle cells: packed uint64 keys (little-endian), ascending."""
    seen_age: bytes = b""
    """Per obstacle cell, float32: seconds before ``t`` it last had a return."""
    near_age: bytes = b""
    """Per obstacle cell, float32: seconds before ``t`` it last had a return from nearer
    than the map's ``near_range`` (``inf``: never)."""
    look_cell: Annotated[float, msgspec.Meta(gt=0, le=100)] = 0.25
    looked: bytes = b""
    """Looked-at cells: packed uint64 keys, ascending."""
    looked_age: bytes = b""
    """Per looked-at cell, float32: seconds before ``t`` a beam last crossed it."""
    sector_age: bytes = b""
    """Per world-frame sector (sector ``i`` covers ``[-pi + i w, -pi + (i + 1) w)``,
    ``w = 2 pi / count``), float32: seconds before ``t`` a beam last returned along it
    (``inf``: never). Empty: no scan yet."""

    def __post_init__(self) -> None:
        if not math.isfinite(self.t):
            raise ValueError(f"ObstacleMap.t = {self.t!r}: give the time in finite seconds")
        n, m = len(self.cells), len(self.looked)
        if n % 8 or len(self.seen_age) != n // 2 or len(self.near_age) != n // 2:
            raise ValueError(
                f"ObstacleMap: {n} bytes of cells, {len(self.seen_age)} of seen_age and "
                f"{len(self.near_age)} of near_age do not match (8 bytes per cell key, 4 per "
                "age); build maps with lidar_occlusion.belief.update"
            )
        if m % 8 or len(self.looked_age) != m // 2 or len(self.sector_age) % 4:
            raise ValueError(
                f"ObstacleMap: {m} bytes of looked, {len(self.looked_age)} of looked_age and "
                f"{len(self.sector_age)} of sector_age do not match (8 bytes per key, 4 per "
                "age); build maps with lidar_occlusion.belief.update"
            )

    # -- reading ---------------------------------------------------------------------------

    @property
    def size(self) -> int:
        """Obstacle cells held."""
        return len(self.cells) // 8

    def keys(self) -> Keys:
        return np.frombuffer(self.cells, _KEY)

    def obstacles(self) -> F:
        """Centres of the obstacle cells, shape (K, 2), world frame."""
        return _centres(self.keys(), self.cell)

    def seen_ages(self, now: float | None = None) -> F:
        """Per obstacle cell: seconds before ``now`` (default: the map's time) it last
        had a return."""
        return np.frombuffer(self.seen_age, _AGE).astype(np.float64) + _since(self, now)

    def near_ages(self, now: float | None = None) -> F:
        """Per obstacle cell: seconds before ``now`` it last had a return from within
        the map's near range (``inf``: never)."""
        return np.frombuffer(self.near_age, _AGE).astype(np.float64) + _since(self, now)

    def looked_recently(
        self, points: npt.ArrayLike, now: float, within_s: float
    ) -> npt.NDArray[np.bool_]:
        """Per world-frame point (shape (K, 2)): whether a beam crossed its looked-at cell
        in the ``within_s`` s before ``now``."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        keys, ok = _keys(pts[:, 0], pts[:, 1], self.look_cell)
        have = np.frombuffer(self.looked, _KEY)
        ages = np.frombuffer(self.looked_age, _AGE).astype(np.float64) + _since(self, now)
        out = np.zeros(pts.shape[0], dtype=bool)
        if have.size == 0:
            return out
        idx = np.minimum(np.searchsorted(have, keys), have.size - 1)
        found = ok & (have[idx] == keys)
        out[found] = ages[idx[found]] <= within_s
        return out

    def seen_recently(
        self, heading_world: float, half_width: float, now: float, within_s: float
    ) -> bool:
        """Whether every world-frame direction within ``half_width`` rad of
        ``heading_world`` had a beam return along it in the ``within_s`` s before
        ``now`` (a direction is one of the map's sectors; any position of the robot)."""
        ages = np.frombuffer(self.sector_age, _AGE)
        count = ages.size
        if count == 0 or not (math.isfinite(heading_world) and math.isfinite(half_width)):
            return False
        width = 2 * math.pi / count
        half = min(max(half_width, 0.0), math.pi)
        lo = math.floor((heading_world - half + math.pi) / width)
        hi = math.floor((heading_world + half + math.pi) / width)
        idx = np.arange(lo, min(hi, lo + count - 1) + 1) % count
        since = _since(self, now)
        return bool(np.all(ages[idx].astype(np.float64) + since <= within_s))


def _since(m: ObstacleMap, now: float | None) -> float:
    return 0.0 if now is None else now - m.t


def _keys(x: F, y: F, cell: float) -> tuple[Keys, npt.NDArray[np.bool_]]:
    """Cell keys of world points, and which points have one (finite, within +-2^31
    cells of the origin)."""
    with np.errstate(invalid="ignore", over="ignore"):
        fx, fy = np.floor(x / cell), np.floor(y / cell)
    lim = float(_OFFSET - 1)
    ok = np.isfinite(fx) & np.isfinite(fy) & (np.abs(fx) < lim) & (np.abs(fy) < lim)
    ix = np.where(ok, fx, 0.0).astype(np.int64) + _OFFSET
    iy = np.where(ok, fy, 0.0).astype(np.int64) + _OFFSET
    keys = (ix.astype(np.uint64) << np.uint64(32)) | iy.astype(np.uint64)
    return keys, ok


def _centres(keys: Keys, cell: float) -> F:
    ix = (keys >> np.uint64(32)).astype(np.int64) - _OFFSET
    iy = (keys & np.uint64(0xFFFFFFFF)).astype(np.int64) - _OFFSET
    return np.column_stack(((ix + 0.5) * cell, (iy + 0.5) * cell))


def _merge(
    keys: Keys, ages: list[F], new: Keys, new_ages: list[F], ttl: float, limit: int
) -> tuple[Keys, list[F]]:
    """Old cells (ascending ``keys``, per-cell ``ages``) and new ones (unique ``new``):
    each column of ages takes the smaller age where a cell is in both; cells whose first
    age is over ``ttl`` go, then the oldest beyond ``limit``. Returns ascending keys."""
    keys_all = np.concatenate([keys, new])
    cols = [np.concatenate([a, b]) for a, b in zip(ages, new_ages, strict=True)]
    order = np.argsort(keys_all, kind="stable")
    keys_all = keys_all[order]
    cols = [c[order] for c in cols]
    if keys_all.size:
        start = np.concatenate([[True], keys_all[1:] != keys_all[:-1]])
        first = np.flatnonzero(start)
        keys_all = keys_all[first]
        cols = [np.minimum.reduceat(c, first) for c in cols]
    keep = cols[0] <= ttl
    if np.count_nonzero(keep) > limit:
        by_age = np.argsort(np.where(keep, cols[0], np.inf), kind="stable")[:limit]
        keep = np.zeros_like(keep)
        keep[by_age] = True
    return keys_all[keep], [c[keep] for c in cols]


def _pack_ages(a: F) -> bytes:
    return bytes(a.astype(_AGE).tobytes())


def update(
    prev: ObstacleMap | None, scan: LaserScan, pose: Pose2D, t_s: float, cfg: MapConfig
) -> ObstacleMap:
    """The map after ``scan``, taken at odometry ``pose`` at ``t_s`` s (pure: ``prev``
    is left as it was). A map built with other cell sizes or sector count than ``cfg``
    starts over; a scan older than the map ages from the map's time."""
    if not (math.isfinite(t_s) and math.isfinite(pose.x + pose.y + pose.theta)):
        raise ValueError(
            f"update: pose ({pose.x}, {pose.y}, {pose.theta}) at t {t_s} is not finite; "
            "give the odometry pose and the scan time in finite numbers"
        )
    if prev is not None and (
        prev.cell != cfg.cell
        or prev.look_cell != cfg.look_cell
        or len(prev.sector_age) not in (0, 4 * cfg.sectors)
    ):
        prev = None
    now = t_s if prev is None else max(prev.t, t_s)
    shift = 0.0 if prev is None else now - prev.t  # old ages grow by this
    age = now - t_s  # what this scan's observations are aged at

    ranges = np.asarray(scan.values(), dtype=np.float64)
    n = ranges.size
    world = pose.theta + scan.angle_min + np.arange(n, dtype=np.float64) * scan.angle_increment
    returned = np.isfinite(ranges)
    r = ranges[returned]
    cos, sin = np.cos(world[returned]), np.sin(world[returned])

    # obstacles: where returns landed
    mapped = r <= cfg.max_range
    hx, hy = pose.x + r[mapped] * cos[mapped], pose.y + r[mapped] * sin[mapped]
    hit_keys, ok = _keys(hx, hy, cfg.cell)
    near = (r[mapped] < cfg.near_range)[ok]
    hit_keys = hit_keys[ok]
    uniq, inverse = np.unique(hit_keys, return_inverse=True)
    near_any = np.zeros(uniq.size, dtype=bool)
    np.logical_or.at(near_any, inverse, near)
    new_seen = np.full(uniq.size, age)
    new_near = np.where(near_any, age, np.inf)

    if prev is None:
        old_keys: Keys = np.zeros(0, np.uint64)
        old_seen = old_near = np.zeros(0)
    else:
        old_keys = prev.keys()
        old_seen = prev.seen_ages(now)
        old_near = prev.near_ages(now)
    keys, (seen, near_ages) = _merge(
        old_keys, [old_seen, old_near], uniq, [new_seen, new_near], cfg.ttl_s, cfg.max_cells
    )

    # free space: the cells the beams crossed up to their returns
    step = cfg.look_cell / 2
    along = np.arange(0.0, cfg.look_range, step)
    reach = np.minimum(r, cfg.look_range)
    crossed = along[None, :] <= reach[:, None]
    d = np.broadcast_to(along[None, :], crossed.shape)[crossed]
    lx = pose.x + d * np.broadcast_to(cos[:, None], crossed.shape)[crossed]
    ly = pose.y + d * np.broadcast_to(sin[:, None], crossed.shape)[crossed]
    ends_x, ends_y = pose.x + reach * cos, pose.y + reach * sin
    look_keys, lok = _keys(
        np.concatenate([lx, ends_x]), np.concatenate([ly, ends_y]), cfg.look_cell
    )
    look_new = np.unique(look_keys[lok])
    if prev is None:
        old_look: Keys = np.zeros(0, np.uint64)
        old_look_age = np.zeros(0)
    else:
        old_look = np.frombuffer(prev.looked, _KEY)
        old_look_age = np.frombuffer(prev.looked_age, _AGE).astype(np.float64) + shift
    looked, (look_age,) = _merge(
        old_look,
        [old_look_age],
        look_new,
        [np.full(look_new.size, age)],
        cfg.ttl_s,
        cfg.max_looked,
    )

    # directions looked along
    if prev is None or not prev.sector_age:
        sectors = np.full(cfg.sectors, np.inf)
    else:
        sectors = np.frombuffer(prev.sector_age, _AGE).astype(np.float64) + shift
    width = 2 * math.pi / cfg.sectors
    sec = np.floor(np.mod(world[returned] + math.pi, 2 * math.pi) / width).astype(np.intp)
    sec = np.clip(sec, 0, cfg.sectors - 1)
    np.minimum.at(sectors, sec, age)

    return ObstacleMap(
        t=now,
        cell=cfg.cell,
        cells=bytes(keys.astype(_KEY).tobytes()),
        seen_age=_pack_ages(seen),
        near_age=_pack_ages(near_ages),
        look_cell=cfg.look_cell,
        looked=bytes(looked.astype(_KEY).tobytes()),
        looked_age=_pack_ages(look_age),
        sector_age=_pack_ages(sectors),
    )


class LidarBelief(Message, frozen=True):
    """What the twin rolls a plan out from: the robot's state as the robot knows it."""

    TYPE = "lidar_occlusion.LidarBelief/1"

    robot: str
    pose: Pose2D
    """Odometry pose (world frame, x forward, counter-clockwise positive)."""
    v: float = 0.0
    """Linear velocity, m/s."""
    w: float = 0.0
    """Angular velocity, rad/s."""
    map: ObstacleMap = msgspec.field(default_factory=ObstacleMap)
    mask: LidarMask | None = None
    """The analysis's current occlusion mask (robot frame), or None: nothing occluded."""
    route: list[tuple[float, float]] = msgspec.field(default_factory=list)
    """The route's waypoints (x, y), world frame, in order."""
    waypoint: int | None = None
    """Index in ``route`` of the waypoint the robot heads for; None: the twin takes the
    one ending the route segment nearest the robot."""
    loop_route: bool = False
    radius: float = 0.17
    """The robot's radius, m."""
    angle_min: float = -math.pi
    angle_increment: float = 2 * math.pi / 360
    beams: int = 360
    range_max: float = 12.0
    t: float = 0.0
    """Seconds (the robot's clock) the belief is of."""


def belief_of(
    robot: str,
    odom: Odometry,
    scan: LaserScan,
    obstacle_map: ObstacleMap,
    mask: LidarMask | None,
    route: list[tuple[float, float]],
    *,
    radius: float = 0.17,
    waypoint: int | None = None,
    loop_route: bool = False,
) -> LidarBelief:
    """A belief from the robot's odometry, its last scan (geometry and time), the map
    and the current mask."""
    return LidarBelief(
        robot=robot,
        pose=odom.pose,
        v=odom.twist.linear,
        w=odom.twist.angular,
        map=obstacle_map,
        mask=mask,
        route=[(float(x), float(y)) for x, y in route],
        waypoint=waypoint,
        loop_route=loop_route,
        radius=radius,
        angle_min=scan.angle_min,
        angle_increment=scan.angle_increment,
        beams=scan.beams,
        range_max=scan.range_max,
        t=scan.stamp / 1e9,
    )


register(ObstacleMap, LidarBelief)
