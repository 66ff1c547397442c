"""The ``lookahead`` planner: turn only as far as it takes to see the route ahead.

The reference planner (:mod:`lidar_occlusion.planning`) sweeps the whole occluded span
on every anomaly, a full turn when that exceeds pi. This one asks what the occlusion
hides that matters - the *corridor ahead*: the route from the robot through its next
waypoints, ``width`` m either side of it, from ``near`` to ``reach`` m along it - and
whether that was seen recently.

Geometry (robot frame as in :mod:`lidar_occlusion.analysis`: x forward, counter-clockwise
positive). The occlusion is fixed to the robot and the lidar sees all around, so turning
counter-clockwise by ``r`` moves a world direction at bearing ``b`` to ``b - r``: a hidden
direction is uncovered once ``b - r`` lands on a visible beam, at least ``edge`` rad
inside the visible arc (the band behind the robot never counts as visible). For each
hidden direction of the corridor the smallest turn each way that uncovers it is read off
the mask; the plan is the cheapest sweep ``[lo, hi]`` (``lo <= 0 <= hi``) that uncovers
every one of them, each end turned ``speed * scan_period / 2`` further so that a scan
falls while the direction is uncovered:

- nothing of the corridor hidden, or every hidden direction seen within ``recent_s``:
  no rotation (an empty plan: nominal navigation);
- one side: ``[hi, -hi]`` or ``[lo, -lo]``; both sides: first toward the side where the
  hidden part of the corridor lies, then across, then back (net rotation exactly zero);
- a full turn ``[2 pi]`` when that is cheaper (net rotation zero modulo 2 pi);
- never more rotation than the reference's plan for the same mask: where the sweep
  would turn further (an occlusion no wider than the corridor: the reference's sweep
  just reaches its edges, without the margins), the reference's rotations are used;
- nothing visible outside the band behind the robot (whose beams the analysis never
  judges): the reference's rotations too - a turn may show what the band hides.

Inputs are small and explicit: the occlusion mask (the analysis's, robot frame), the
robot's pose (:class:`rap_schemas.Pose2D`, world frame), the route still ahead (waypoints
``(x, y)``, next first) and a record of what was seen when - anything with
``seen_recently(heading_world, half_width, now, within_s)`` (:class:`SeenRecord`): the
:class:`SeenSectors` here, built by :func:`see` from masks and poses, or a belief map
with the same method.

Decided every scan, not only on an anomaly (:class:`Lookahead`): a plan skipped because
the corridor was seen recently is proposed the scan that the record goes stale, and a
plan in force is decided anew (with the pose of the moment) when its period ends.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import msgspec
import numpy as np
import numpy.typing as npt
from rap_schemas import Pose2D, SpinPlan

from .analysis import signed_angles
from .planning import LookaheadConfig, PlanConfig, commands_for, rotations

__all__ = [
    "Lookahead",
    "SeenRecord",
    "SeenSectors",
    "corridor_beams",
    "lookahead_rotations",
    "plan_lookahead",
    "see",
]

TWO_PI = 2 * math.pi
Mask = npt.NDArray[np.bool_]
Point = tuple[float, float]


def _wrap(a: float) -> float:
    """Into (-pi, pi]."""
    return math.pi - (math.pi - a) % TWO_PI


class SeenRecord(Protocol):
    """What a planner asks of a record of what was seen when."""

    def seen_recently(
        self, heading_world: float, half_width: float, now: float, within_s: float
    ) -> bool:
        """Was every world heading within ``half_width`` rad of ``heading_world`` seen
        unoccluded at most ``within_s`` s before ``now`` (s)?"""
        ...


class SeenSectors(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """World-frame headings last seen unoccluded, in ``len(times)`` equal bins, and
    from where.

    ``times[i]`` is the time (s) bin ``i`` - headings ``[-pi + i w, -pi + (i + 1) w)``,
    ``w = 2 pi / len(times)`` - was last seen whole (``-inf``: never); ``xs[i]``,
    ``ys[i]`` where the robot was then (world frame, m). Built by :func:`see`."""

    times: list[float]
    xs: list[float]
    ys: list[float]

    def __post_init__(self) -> None:
        if not self.times or len(self.xs) != len(self.times) or len(self.ys) != len(self.times):
            raise ValueError(
                f"SeenSectors needs times, xs and ys of one length of at least 1, got "
                f"{len(self.times)}, {len(self.xs)} and {len(self.ys)}"
            )

    @classmethod
    def empty(cls, bins: int) -> SeenSectors:
        return cls([-math.inf] * bins, [0.0] * bins, [0.0] * bins)

    def _bins(self, heading_world: float, half_width: float) -> Sequence[int]:
        n = len(self.times)
        if 2 * half_width >= TWO_PI:
            return range(n)
        w = TWO_PI / n
        lo = _wrap(heading_world - half_width) + math.pi
        return [i % n for i in range(math.floor(lo / w), math.floor((lo + 2 * half_width) / w) + 1)]

    def seen_recently(
        self, heading_world: float, half_width: float, now: float, within_s: float
    ) -> bool:
        return all(now - self.times[i] <= within_s for i in self._bins(heading_world, half_width))

    def seen_from_near(
        self,
        heading_world: float,
        half_width: float,
        now: float,
        within_s: float,
        x: float,
        y: float,
        within_m: float,
    ) -> bool:
        """:meth:`seen_recently`, and from within ``within_m`` m of ``(x, y)``."""
        return all(
            now - self.times[i] <= within_s
            and math.hypot(self.xs[i] - x, self.ys[i] - y) <= within_m
            for i in self._bins(heading_world, half_width)
        )


def _visible(
    occluded: Mask, angles: npt.NDArray[np.float64], ignore_from: float
) -> npt.NDArray[np.bool_]:
    vis: npt.NDArray[np.bool_] = ~occluded & (np.abs(angles) <= ignore_from)
    return vis


def see(
    seen: SeenSectors | None,
    occluded: Sequence[bool] | Mask,
    angle_min: float,
    angle_increment: float,
    pose: Pose2D,
    now: float,
    cfg: LookaheadConfig,
) -> SeenSectors:
    """``seen`` updated with one scan's mask taken at ``pose`` at time ``now``: a bin
    whose beams are all unoccluded (and outside the band behind the robot) is seen now,
    from the pose's position."""
    mask = np.asarray(occluded, dtype=bool)
    record = seen if seen is not None and len(seen.times) == cfg.bins else None
    if record is None:
        record = SeenSectors.empty(cfg.bins)
    if mask.size == 0:
        return record
    times = np.asarray(record.times, dtype=np.float64)
    xs, ys = np.asarray(record.xs), np.asarray(record.ys)
    angles = signed_angles(angle_min, angle_increment, mask.size)
    visible = _visible(mask, angles, cfg.ignore_from)
    world = np.mod(pose.theta + angles + math.pi, TWO_PI)
    idx = np.minimum((world / (TWO_PI / cfg.bins)).astype(np.intp), cfg.bins - 1)
    beams = np.bincount(idx, minlength=cfg.bins)
    clear = np.bincount(idx, weights=visible.astype(np.float64), minlength=cfg.bins)
    whole = (beams > 0) & (clear == beams)
    times[whole], xs[whole], ys[whole] = now, pose.x, pose.y
    return SeenSectors(times.tolist(), xs.tolist(), ys.tolist())


def _along(
    start: Point, route: Sequence[Point], distances: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Points at ``distances`` along the polyline start -> route, and the unit direction
    of the leg each lies on (past the last waypoint: its leg, extended)."""
    pts = np.array([start, *route], dtype=np.float64)
    legs = np.diff(pts, axis=0)
    lengths = np.hypot(legs[:, 0], legs[:, 1])
    keep = lengths > 1e-9
    pts = np.vstack([pts[:1], pts[1:][keep]])
    legs, lengths = legs[keep], lengths[keep]
    if lengths.size == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    ends = np.cumsum(lengths)
    leg = np.minimum(np.searchsorted(ends, distances, side="right"), lengths.size - 1)
    offset = distances - (ends[leg] - lengths[leg])
    unit = legs[leg] / lengths[leg][:, None]
    return pts[leg] + unit * offset[:, None], unit


def corridor_beams(
    pose: Pose2D,
    route: Sequence[Point],
    angle_min: float,
    angle_increment: float,
    beams: int,
    cfg: LookaheadConfig,
) -> Mask:
    """True for each beam (robot frame) that looks into the corridor ahead: ``cfg.width``
    m either side of the route from the robot through ``route``, from ``cfg.near`` to
    ``cfg.reach`` m along it. No route ahead: none."""
    need = np.zeros(beams, dtype=bool)
    if not route or beams == 0 or cfg.reach <= cfg.near:
        return need
    step = max(min(0.05, cfg.width / 2), 1e-3)
    s = np.arange(cfg.near, cfg.reach + step / 2, step)
    centre, unit = _along((pose.x, pose.y), route, s)
    if centre.size == 0:
        return need
    normal = np.column_stack((-unit[:, 1], unit[:, 0]))
    angles = signed_angles(angle_min, angle_increment, beams)
    left = centre + cfg.width * normal
    right = centre - cfg.width * normal
    bl = np.arctan2(left[:, 1] - pose.y, left[:, 0] - pose.x) - pose.theta
    br = np.arctan2(right[:, 1] - pose.y, right[:, 0] - pose.x) - pose.theta
    bc = np.arctan2(centre[:, 1] - pose.y, centre[:, 0] - pose.x) - pose.theta
    for lo_, hi_, c_ in zip(br, bl, bc, strict=True):
        # the arc from one edge to the other that holds the centre line
        lo, width = float(lo_), float(np.mod(hi_ - lo_, TWO_PI))
        if np.mod(c_ - lo_, TWO_PI) > width:
            lo, width = float(hi_), TWO_PI - width
        need |= np.mod(angles - lo, TWO_PI) <= width
    return need


def _first_true(
    vis: npt.NDArray[np.bool_], start: npt.NDArray[np.intp], sign: int
) -> npt.NDArray[np.intp]:
    """Per start index: the fewest beams to step (``sign`` -1 down, +1 up, circularly)
    to reach a True of ``vis``."""
    n = vis.size
    where = np.flatnonzero(vis)
    steps = np.mod(sign * (where[None, :] - start[:, None]), n)
    out: npt.NDArray[np.intp] = steps.min(axis=1)
    return out


def lookahead_rotations(
    occluded: Sequence[bool] | Mask,
    angle_min: float,
    angle_increment: float,
    pose: Pose2D,
    route: Sequence[Point],
    seen: SeenRecord | None,
    now: float,
    cfg: LookaheadConfig,
) -> list[float]:
    """The rotation sequence (rad, counter-clockwise positive) that uncovers the hidden
    part of the corridor ahead (see the module docstring)."""
    mask = np.asarray(occluded, dtype=bool)
    n = mask.size
    if n == 0 or not mask.any():
        return []
    angles = signed_angles(angle_min, angle_increment, n)
    hidden = corridor_beams(pose, route, angle_min, angle_increment, n, cfg) & mask
    if seen is not None:
        for j in np.flatnonzero(hidden):
            heading = _wrap(pose.theta + float(angles[j]))
            if isinstance(seen, SeenSectors):
                known = seen.seen_from_near(
                    heading, angle_increment / 2, now, cfg.recent_s, pose.x, pose.y, cfg.moved
                )
            else:
                known = seen.seen_recently(heading, angle_increment / 2, now, cfg.recent_s)
            if known:
                hidden[j] = False
    if not hidden.any():
        return []
    visible = _visible(mask, angles, cfg.ignore_from)
    k = math.ceil(cfg.edge / angle_increment - 1e-9) if angle_increment > 0 else 0
    eroded = visible.copy()
    for s in range(1, min(k, n) + 1):
        eroded &= np.roll(visible, s) & np.roll(visible, -s)
    if not eroded.any():
        # nothing visible outside the band behind the robot, which the mask cannot
        # judge: the reference's plan (a sweep, or a full turn) is all that may help
        return rotations(angles[mask])
    idx = np.flatnonzero(hidden)
    ccw = _first_true(eroded, idx, -1) * angle_increment  # turn left: bearing decreases
    cw = _first_true(eroded, idx, +1) * angle_increment  # turn right: bearing increases
    b = angles[idx]
    side = 1 if float(np.sin(b).sum()) >= 0 else -1  # where the hidden part lies
    over = cfg.speed * cfg.scan_period / 2
    best: tuple[float, int, float, float] | None = None
    for hi in sorted({0.0, *(float(v) for v in ccw)}):
        rest = cw[ccw > hi + 1e-12]
        lo = float(rest.max()) if rest.size else 0.0
        h = hi + over if hi > 0 else 0.0
        o = lo + over if lo > 0 else 0.0
        toward = 0 if (side > 0 and h >= o) or (side < 0 and o >= h) else 1
        cand = (h + o, toward, h, o)
        if best is None or cand[:2] < best[:2]:
            best = cand
    assert best is not None
    total, _, hi, lo = best
    if 2 * total >= TWO_PI:
        rots = [TWO_PI * side]
    elif lo == 0.0:
        rots = [hi, -hi]
    elif hi == 0.0:
        rots = [-lo, lo]
    elif side > 0:
        rots = [hi, -(hi + lo), lo]
    else:
        rots = [-lo, lo + hi, -hi]
    ref = rotations(angles[mask])
    if sum(abs(r) for r in rots) > sum(abs(r) for r in ref):
        return ref
    return rots


def plan_lookahead(
    occluded: Sequence[bool] | Mask,
    angle_min: float,
    angle_increment: float,
    pose: Pose2D,
    route: Sequence[Point],
    seen: SeenRecord | None,
    now: float,
    cfg: PlanConfig,
) -> SpinPlan:
    """The spin plan of :func:`lookahead_rotations`, at ``cfg.lookahead.speed``."""
    la = cfg.lookahead
    rots = lookahead_rotations(occluded, angle_min, angle_increment, pose, route, seen, now, la)
    return SpinPlan(commands=commands_for(rots, la.speed), period=cfg.period)


class Lookahead(msgspec.Struct, kw_only=True):
    """What the lookahead plan stage keeps between scans (a snapshot of it restores it).

    Call :meth:`step` on every scan, with that scan's mask and the pose at its time; it
    returns the plan to propose now, or None:

    - on an anomaly (``anomaly=True``): always the fresh plan (possibly empty);
    - while no spin is in force (none proposed yet, or an empty plan): the fresh plan
      as soon as it is not empty (what was seen went stale, or the route turned into
      the occlusion);
    - while a spin is in force: the fresh plan when its period ends (a plan proposed
      then starts at that moment, so the rhythm stays the same).

    :meth:`withdrawn` forgets the plan proposed last (a rejected plan given up on) and
    proposes nothing but on an anomaly for one period."""

    index: int = 0
    """Waypoints passed (within ``reached`` m); on a looping route it goes on counting."""
    seen: SeenSectors | None = None
    plan: SpinPlan | None = None
    """The plan proposed last (None: none, or withdrawn)."""
    since: float = 0.0
    """Time (s) the plan proposed last began."""
    observed: float = -math.inf
    """Time (s) of the last scan observed."""
    hold_until: float = -math.inf
    """Time (s) before which only an anomaly gets a plan (after a withdrawal)."""

    def ahead(self, route: Sequence[Point], loop: bool = False) -> list[Point]:
        """The waypoints still ahead, next first (a looping route: all of them, round)."""
        if not loop:
            return list(route[self.index :])
        i = self.index % len(route) if route else 0
        return [*route[i:], *route[:i]]

    def observe(
        self,
        occluded: Sequence[bool] | Mask,
        angle_min: float,
        angle_increment: float,
        pose: Pose2D,
        route: Sequence[Point],
        now: float,
        cfg: LookaheadConfig,
        loop: bool = False,
    ) -> None:
        """Record what the scan at ``now`` saw and how far along the route the robot is
        (once per scan: a second call for the same ``now`` does nothing)."""
        if now == self.observed:
            return
        self.observed = now
        self.seen = see(self.seen, occluded, angle_min, angle_increment, pose, now, cfg)
        for _ in range(len(route)):
            if not loop and self.index >= len(route):
                break
            x, y = route[self.index % len(route)]
            if math.hypot(x - pose.x, y - pose.y) >= cfg.reached:
                break
            self.index += 1

    def step(
        self,
        occluded: Sequence[bool] | Mask,
        angle_min: float,
        angle_increment: float,
        pose: Pose2D,
        route: Sequence[Point],
        now: float,
        cfg: PlanConfig,
        *,
        anomaly: bool = False,
        seen: SeenRecord | None = None,
        loop: bool = False,
    ) -> SpinPlan | None:
        """The plan to propose after the scan at ``now`` (s), or None. ``route``: the
        whole route (``cfg.route``), ``loop``: whether it repeats (``cfg.loop_route``).
        ``seen``: a record to ask instead of this one's own (a belief map); this one is
        kept either way."""
        la = cfg.lookahead
        self.observe(occluded, angle_min, angle_increment, pose, route, now, la, loop)
        if not anomaly and now < self.hold_until:
            return None
        in_force = self.plan is not None and bool(self.plan.commands)
        if not anomaly and in_force:
            assert self.plan is not None
            ended = now - self.since >= self.plan.period - la.scan_period / 2
            if not ended:
                return None
        record: SeenRecord | None = seen if seen is not None else self.seen
        ahead = self.ahead(route, loop)
        fresh = plan_lookahead(occluded, angle_min, angle_increment, pose, ahead, record, now, cfg)
        if not anomaly and not in_force and not fresh.commands:
            return None
        self.plan, self.since = fresh, now
        return fresh

    def withdrawn(self, now: float, cfg: PlanConfig) -> None:
        """The plan proposed last did not run (rejected and given up on, at ``now``)."""
        self.plan = None
        self.hold_until = now + cfg.period
