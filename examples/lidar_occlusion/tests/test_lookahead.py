"""The lookahead planner as pure functions: examples and invariants."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lidar_occlusion.analysis import signed_angles
from lidar_occlusion.lookahead import (
    Lookahead,
    SeenSectors,
    corridor_beams,
    lookahead_rotations,
    plan_lookahead,
    see,
)
from lidar_occlusion.planning import (
    LegitimacyConfig,
    LookaheadConfig,
    PlanConfig,
    check_plan,
    plan_for,
    rotations,
)
from rap_schemas import PlanProposal, Pose2D, SpinPlan

N = 360
INC = 2 * math.pi / N
ANGLES = signed_angles(-math.pi, INC, N)
LA = LookaheadConfig()
CFG = PlanConfig(planner="lookahead")
HOME = Pose2D(x=0.0, y=0.0, theta=0.0)
EAST = [(5.0, 0.0)]
"""A route straight ahead of the robot at HOME."""


def arc(start: float, width: float) -> np.ndarray:
    """True on the beams of the arc (start, width), robot frame."""
    return np.mod(ANGLES - start, 2 * math.pi) < width


def rots(
    mask: np.ndarray,
    pose: Pose2D = HOME,
    route: list[tuple[float, float]] = EAST,
    seen: SeenSectors | None = None,
    now: float = 0.0,
) -> list[float]:
    return lookahead_rotations(mask, -math.pi, INC, pose, route, seen, now, LA)


def uncovered(mask: np.ndarray, r: list[float], cfg: LookaheadConfig = LA) -> np.ndarray:
    """Per beam: does turning through the sweep ``r`` bring it (as a world direction)
    onto a visible beam, outside the band behind the robot, at some moment?"""
    visible = ~mask & (np.abs(ANGLES) <= cfg.ignore_from)
    heading, reached = 0.0, [0.0]
    for turn in r:
        fractions = np.linspace(0, 1, int(abs(turn) / (INC / 4)) + 2)[1:]
        reached.extend(heading + f * turn for f in fractions)
        heading += turn
    out = np.zeros(N, dtype=bool)
    for h in reached:
        moved = np.mod(ANGLES - h + math.pi, 2 * math.pi) - math.pi  # bearing after turning h
        idx = np.round((moved + math.pi) / INC).astype(int) % N
        out |= visible[idx]
    return out


# -- geometry of the corridor ------------------------------------------------------------


def test_the_corridor_ahead_is_a_cone_around_the_route() -> None:
    need = corridor_beams(HOME, EAST, -math.pi, INC, N, LA)
    half = math.atan(LA.width / LA.near)  # widest at the near end
    assert need[np.abs(ANGLES) < half - INC].all()
    assert not need[np.abs(ANGLES) > half + INC].any()
    facing_north = Pose2D(x=0.0, y=0.0, theta=math.pi / 2)
    turned = corridor_beams(facing_north, EAST, -math.pi, INC, N, LA)
    assert turned[np.abs(ANGLES + math.pi / 2) < INC].all()  # the route is on the right
    assert not turned[np.abs(ANGLES) < INC].any()


def test_the_corridor_follows_the_route_round_a_corner() -> None:
    corner = [(1.0, 0.0), (1.0, 5.0)]  # 1 m ahead, then left
    need = corridor_beams(HOME, corner, -math.pi, INC, N, LA)
    assert need[np.abs(ANGLES - math.atan2(1.0, 1.0)) < INC].all()  # the next leg
    assert not corridor_beams(HOME, [], -math.pi, INC, N, LA).any()  # route done


# -- the plan ------------------------------------------------------------------------------


def test_no_spin_when_the_route_ahead_is_visible() -> None:
    behind_left = arc(1.5, 0.7)
    assert rotations(ANGLES[behind_left])  # the reference spins
    assert rots(behind_left) == []
    assert rots(np.zeros(N, dtype=bool)) == []


def test_it_turns_toward_the_occluded_part_of_the_route_ahead() -> None:
    left = arc(-0.1, 1.5)  # covers straight ahead, mostly on the left
    r = rots(left)
    assert r
    assert r[0] > 0
    right = arc(-1.4, 1.5)  # the mirror image
    r = rots(right)
    assert r
    assert r[0] < 0
    half_left = arc(0.2, 0.5)  # only the left half of the corridor is hidden
    r = rots(half_left)
    assert r
    assert r[0] > 0


def test_the_sweep_uncovers_every_hidden_direction_of_the_corridor() -> None:
    need = corridor_beams(HOME, EAST, -math.pi, INC, N, LA)
    for mask in (arc(-0.1, 1.5), arc(-1.4, 1.5), arc(-1.0, 2.5), arc(0.2, 0.5)):
        r = rots(mask)
        ref = rotations(ANGLES[mask])
        assert r
        assert sum(abs(x) for x in r) < sum(abs(x) for x in ref)
        hidden = need & mask
        assert uncovered(mask, r)[hidden].all(), (r, ANGLES[hidden & ~uncovered(mask, r)])


def test_where_uncovering_all_of_it_costs_more_than_the_reference_the_reference_it_is() -> None:
    # the arc is the corridor's width: the reference's sweep just reaches its edges,
    # the lookahead's (a margin inside, past the scan spacing) would turn further
    tight = arc(-0.1, 0.7)
    assert rots(tight) == rotations(ANGLES[tight])


def test_a_narrow_window_is_used_and_the_band_behind_alone_means_the_reference() -> None:
    window_behind_right = arc(-1.3, 2 * math.pi - 0.9)  # visible only at -2.2..-1.3 rad
    r = rots(window_behind_right)
    assert r
    assert sum(abs(x) for x in r) < 2 * math.pi
    need = corridor_beams(HOME, EAST, -math.pi, INC, N, LA)
    assert uncovered(window_behind_right, r)[need].all()
    # visible only behind, in the band the mask cannot judge: the reference's full turn
    only_band = arc(-math.pi + 0.3, 2 * math.pi - 0.6)
    assert rots(only_band) == rotations(ANGLES[only_band]) == [2 * math.pi]


def test_no_spin_when_the_route_ahead_was_seen_recently() -> None:
    front = arc(-0.3, 0.8)
    seen = see(None, np.zeros(N, dtype=bool), -math.pi, INC, HOME, 10.0, LA)
    assert rots(front, seen=seen, now=10.0 + LA.recent_s - 0.1) == []
    assert rots(front, seen=seen, now=10.0 + LA.recent_s + 0.5) == rots(front)
    # seen from another heading: the record is in the world frame
    turned = Pose2D(x=0.0, y=0.0, theta=1.0)
    seen_turned = see(None, arc(0.5, 1.0), -math.pi, INC, turned, 10.0, LA)
    assert rots(front, seen=seen_turned, now=11.0) == []
    # seen from farther back than `moved`: what lies ahead now was beyond the navigation's
    # memory then
    ahead = Pose2D(x=LA.moved + 0.1, y=0.0, theta=0.0)
    assert rots(front, pose=ahead, seen=seen, now=11.0) == rots(front, pose=ahead)
    assert rots(front, pose=ahead, seen=seen, now=11.0) != []


def test_a_direction_seen_only_in_part_or_behind_is_not_seen() -> None:
    seen = see(None, arc(-0.3, 0.8), -math.pi, INC, HOME, 0.0, LA)
    assert not seen.seen_recently(0.0, 0.01, 0.5, 5.0)  # occluded: not seen
    assert seen.seen_recently(1.5, 0.1, 0.5, 5.0)
    assert not seen.seen_recently(math.pi, 0.01, 0.5, 5.0)  # the band behind the robot
    assert not seen.seen_recently(1.5, 0.1, 6.0, 5.0)  # too long ago
    assert not SeenSectors.empty(LA.bins).seen_recently(1.5, 0.1, 0.0, 5.0)
    wrapped = see(None, np.zeros(N, dtype=bool), -math.pi, INC, Pose2D(x=0, y=0, theta=3.0), 0, LA)
    assert wrapped.seen_recently(-math.pi + 0.05, 0.2, 0.0, 1.0)  # across +-pi


masks = st.lists(
    st.tuples(st.floats(-math.pi, math.pi), st.floats(0.05, 2 * math.pi)), min_size=1, max_size=3
).map(lambda arcs: np.logical_or.reduce([arc(s, w) for s, w in arcs]))
poses = st.builds(
    Pose2D,
    x=st.floats(-3, 3),
    y=st.floats(-3, 3),
    theta=st.floats(-math.pi, math.pi),
)
routes = st.lists(st.tuples(st.floats(-6, 6), st.floats(-6, 6)), min_size=0, max_size=3)


@settings(max_examples=150, deadline=None)
@given(mask=masks, pose=poses, route=routes)
def test_never_more_than_the_reference_and_back_where_it_started(
    mask: np.ndarray, pose: Pose2D, route: list[tuple[float, float]]
) -> None:
    r = rots(mask, pose, route)
    ref = rotations(ANGLES[mask])
    assert sum(abs(x) for x in r) <= sum(abs(x) for x in ref) + 1e-9
    net = math.remainder(sum(r), 2 * math.pi)
    assert abs(net) < 1e-9  # net rotation zero modulo 2 pi
    plan = plan_lookahead(mask, -math.pi, INC, pose, route, None, 0.0, CFG)
    reference = plan_for(mask, -math.pi, INC, PlanConfig())
    assert (
        sum(c.duration for c in plan.commands) <= sum(c.duration for c in reference.commands) + 1e-9
    )
    # every command within the robot's limit, the commands within the period
    assert all(abs(c.omega) <= LegitimacyConfig().max_angular for c in plan.commands)
    proposal = PlanProposal(
        plan_uid=b"u" * 16, plan_type=plan.TYPE, plan=plan, proposer="p", created=0
    )
    assert check_plan(proposal, 0, LegitimacyConfig()) is None


# -- deciding every scan -------------------------------------------------------------------


def step(
    la: Lookahead, mask: np.ndarray, now: float, anomaly: bool = False, pose: Pose2D = HOME
) -> SpinPlan | None:
    return la.step(mask, -math.pi, INC, pose, EAST, now, CFG, anomaly=anomaly)


def test_an_anomaly_seen_moments_ago_waits_until_the_record_goes_stale() -> None:
    la = Lookahead()
    clear, front = np.zeros(N, dtype=bool), arc(-0.3, 0.8)
    assert step(la, clear, 0.0) is None  # nothing hidden: nothing to propose
    plan = step(la, front, 0.2, anomaly=True)
    assert plan is not None
    assert plan.commands == []
    t = 0.4
    while (plan := step(la, front, t)) is None:
        t = round(t + 0.2, 1)
        assert t < 10
    assert plan.commands
    assert t == pytest.approx(LA.recent_s + 0.2, abs=0.21)
    # the spin in force: nothing new until its period ends, then decided anew
    assert all(step(la, front, round(t + k * 0.2, 1)) is None for k in range(1, 39))
    again = step(la, front, round(t + CFG.period, 1))
    assert again is not None
    assert again.commands


def test_a_spin_in_force_is_stopped_at_its_period_end_when_the_route_turned_clear() -> None:
    la = Lookahead()
    front = arc(-0.3, 0.8)
    plan = step(la, front, 0.0, anomaly=True)  # nothing seen yet: spin now
    assert plan is not None
    assert plan.commands
    facing_away = Pose2D(x=0.0, y=0.0, theta=math.pi / 2)  # the route now on the right
    assert step(la, front, 4.0, pose=facing_away) is None
    stop = step(la, front, CFG.period, pose=facing_away)
    assert stop is not None
    assert stop.commands == []


def test_a_withdrawn_plan_is_not_proposed_again_for_a_period() -> None:
    la = Lookahead()
    front = arc(-0.3, 0.8)
    assert step(la, front, 0.0, anomaly=True) is not None
    la.withdrawn(0.0, CFG)
    assert step(la, front, 0.2) is None
    assert step(la, front, CFG.period - 0.2) is None
    assert step(la, front, 0.4, anomaly=True) is not None  # an anomaly is always answered
    la.withdrawn(0.4, CFG)
    assert step(la, front, 0.4 + CFG.period) is not None


def test_the_route_is_followed_and_a_finished_route_needs_no_spin() -> None:
    la = Lookahead()
    route = [(0.1, 0.0), (5.0, 0.0)]
    front = arc(-0.3, 0.8)
    la.step(front, -math.pi, INC, HOME, route, 0.0, CFG)
    assert la.index == 1  # the first waypoint is within reach: passed
    at_end = Pose2D(x=5.0, y=0.0, theta=0.0)
    plan = la.step(front, -math.pi, INC, at_end, route, 0.2, CFG, anomaly=True)
    assert la.index == 2
    assert plan is not None
    assert plan.commands == []


def test_the_state_survives_a_snapshot() -> None:
    import msgspec

    la = Lookahead()
    step(la, arc(-0.3, 0.8), 0.0, anomaly=True)
    back = msgspec.msgpack.decode(msgspec.msgpack.encode(la), type=Lookahead)
    assert back == la


def test_a_belief_map_can_stand_in_for_the_record() -> None:
    class Everything:
        def seen_recently(
            self, heading_world: float, half_width: float, now: float, within_s: float
        ) -> bool:
            return True

    la = Lookahead()
    plan = la.step(
        arc(-0.3, 0.8), -math.pi, INC, HOME, EAST, 0.0, CFG, anomaly=True, seen=Everything()
    )
    assert plan is not None
    assert plan.commands == []
    assert la.seen is not None  # its own record is kept up to date all the same


def test_a_looping_route_goes_round() -> None:
    la = Lookahead()
    route = [(1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.0, 0.0)]
    front = arc(-0.3, 0.8)
    for t, (x, y) in enumerate([*route, route[0]]):
        la.step(front, -math.pi, INC, Pose2D(x=x, y=y, theta=0.0), route, t, CFG, loop=True)
    assert la.index == 5
    assert la.ahead(route, loop=True) == [*route[1:], route[0]]
    assert la.ahead(route) == []  # not looping: done
