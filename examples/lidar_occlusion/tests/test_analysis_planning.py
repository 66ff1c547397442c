"""The analysis and the planner as pure functions: examples and invariants."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from lidar_occlusion.analysis import (
    AnalysisConfig,
    MaskWindow,
    analyse_scan,
    clean,
    differing_arc,
    is_anomaly,
    raw_mask,
    signed_angles,
)
from lidar_occlusion.planning import (
    LegitimacyConfig,
    PlanConfig,
    check_plan,
    commands_for,
    plan_for,
    rotations,
)
from rap_schemas import LaserScan, PlanProposal, SpinCommand, SpinPlan, pack_ranges

N = 360
INC = 2 * math.pi / N
CFG = AnalysisConfig()
ANGLES = signed_angles(-math.pi, INC, N)


def scan(ranges: np.ndarray) -> LaserScan:
    return LaserScan(
        stamp=0,
        frame_id="tb1/base_link",
        angle_min=-math.pi,
        angle_increment=INC,
        range_min=0.1,
        range_max=12.0,
        ranges=pack_ranges(ranges),
    )


def sector(start: float, width: float) -> np.ndarray:
    """Ranges of 3 m, inf on the beams of the arc (start, width)."""
    r = np.full(N, 3.0)
    r[np.mod(ANGLES - start, 2 * math.pi) < width] = np.inf
    return r


def test_angles_are_signed_and_the_frame_is_explicit() -> None:
    assert ANGLES[0] == pytest.approx(math.pi)  # -pi maps to +pi: (-pi, pi]
    assert ANGLES[180] == pytest.approx(0.0)  # beam 180 looks straight ahead
    assert ANGLES[270] == pytest.approx(math.pi / 2)  # counter-clockwise positive
    assert np.all((ANGLES > -math.pi) & (ANGLES <= math.pi))


def test_raw_mask_is_no_finite_return() -> None:
    assert raw_mask([1.0, math.inf, math.nan, 0.2]).tolist() == [False, True, True, False]


def test_clean_drops_specks_and_fills_gaps() -> None:
    k = round(CFG.radius / INC)  # 4 beams either side
    m = np.zeros(N, dtype=bool)
    m[10:15] = True  # 5 beams: narrower than the 9-beam element -> dropped
    m[100:140] = True
    m[120:123] = False  # a 3-beam gap -> filled
    out = clean(m, k)
    assert not out[10:15].any()
    assert out[100:140].all()
    assert np.count_nonzero(out) == 40


def test_clean_wraps_around_beam_zero() -> None:
    m = np.zeros(N, dtype=bool)
    m[:6] = True
    m[-6:] = True  # one 12-beam arc across the seam
    assert np.array_equal(clean(m, 4), m)


def test_window_threshold_one_scan_in_three_is_enough_and_it_fades() -> None:
    w = MaskWindow(3)
    occ = analyse_scan(scan(sector(-0.3, 0.6)), w, CFG)
    assert np.count_nonzero(occ) > 30  # 1/3 > 0.3
    clear = scan(np.full(N, 3.0))
    assert analyse_scan(clear, w, CFG).any()  # still 1 in 3
    assert analyse_scan(clear, w, CFG).any()
    assert not analyse_scan(clear, w, CFG).any()  # the occluded scan left the window


@given(start=st.floats(-math.pi, math.pi), width=st.floats(0.0, 2 * math.pi))
def test_the_ignore_band_never_triggers(start: float, width: float) -> None:
    r = sector(start, width)
    r[np.abs(ANGLES) <= CFG.ignore_from] = 3.0  # anything outside the band is clear
    w = MaskWindow(3)
    for _ in range(3):
        occ = analyse_scan(scan(r), w, CFG)
    assert not occ.any()
    assert not is_anomaly(occ, None, INC, False, CFG)


def test_anomaly_rule() -> None:
    w = MaskWindow(3)
    occ = analyse_scan(scan(sector(-0.4, 0.8)), w, CFG)
    assert is_anomaly(occ, None, INC, False, CFG)
    assert not is_anomaly(occ, None, INC, True, CFG)  # one is being handled
    assert not is_anomaly(occ, occ.copy(), INC, False, CFG)  # already planned for
    nudged = occ.copy()
    nudged[np.flatnonzero(occ)[:3]] = False  # 3 degrees: not more than pi/48
    assert differing_arc(occ, nudged, INC) == pytest.approx(3 * INC)
    assert not is_anomaly(occ, nudged, INC, False, CFG)
    assert is_anomaly(np.zeros(N, dtype=bool), occ, INC, False, CFG)  # it went away


def test_rotations_cases() -> None:
    assert rotations([]) == []
    assert rotations([0.2, 0.5]) == [0.5, -0.5]
    assert rotations([-0.5, -0.2]) == [-0.5, 0.5]
    assert rotations([-0.4, 0.9]) == pytest.approx([0.9, -1.3, 0.4])  # larger first
    assert rotations([-0.9, 0.4]) == pytest.approx([-0.9, 1.3, -0.4])
    assert rotations([-2.0, 1.5]) == [2 * math.pi]  # span > pi: a full turn


angle_lists = st.lists(
    st.floats(-math.pi, math.pi, exclude_min=True, allow_nan=False), min_size=1, max_size=40
)


@given(angle_lists)
def test_net_rotation_is_zero(angles: list[float]) -> None:
    rots = rotations(angles)
    a = np.asarray(angles)
    x, y = min(a.min(), 0.0), max(a.max(), 0.0)
    if y - x > math.pi:
        assert rots == [2 * math.pi]  # a full turn ends where it began
        assert math.remainder(sum(rots), 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    else:
        assert sum(rots) == pytest.approx(0.0, abs=1e-9)
        if x < 0 < y:
            assert abs(rots[0]) == pytest.approx(max(-x, y))  # larger magnitude first
    # the sequence reaches both ends of the occluded span
    heading, seen = 0.0, [0.0]
    for r in rots:
        heading += r
        seen.append(heading)
    if rots != [2 * math.pi]:
        assert min(seen) == pytest.approx(x)
        assert max(seen) == pytest.approx(y)


@given(angle_lists, st.floats(0.2, 1.9))
def test_durations_match_angles(angles: list[float], speed: float) -> None:
    rots = rotations(angles)
    cmds = commands_for(rots, speed)
    for r, c in zip(rots, cmds, strict=True):
        assert abs(c.omega) == speed
        assert math.copysign(1, c.omega) == math.copysign(1, r)
        assert c.duration * speed == pytest.approx(abs(r))


def test_plan_from_a_mask_at_1_rad_per_s() -> None:
    m = np.zeros(N, dtype=bool)
    m[np.abs(ANGLES - 0.5) < 0.2] = True  # only positive angles 0.3 .. 0.7
    plan = plan_for(m, -math.pi, INC, PlanConfig())
    assert plan.period == 8.0
    assert [c.omega for c in plan.commands] == [1.0, -1.0]
    assert plan.commands[0].duration == pytest.approx(0.7, abs=INC)
    assert plan_for(np.zeros(N, dtype=bool), -math.pi, INC, PlanConfig()).commands == []


def proposal(plan: SpinPlan, created: int = 0) -> PlanProposal[SpinPlan]:
    return PlanProposal(
        plan_uid=b"u" * 16, plan_type=plan.TYPE, plan=plan, proposer="p", created=created
    )


def test_check_plan() -> None:
    cfg = LegitimacyConfig()
    ok = SpinPlan(commands=[SpinCommand(omega=1.0, duration=1.0)], period=8.0)
    assert check_plan(proposal(ok), 0, cfg) is None
    too_long = SpinPlan(commands=[SpinCommand(omega=1.0, duration=8.0)], period=8.0)
    assert "within the period" in (check_plan(proposal(too_long), 0, cfg) or "")
    too_fast = SpinPlan(commands=[SpinCommand(omega=2.5, duration=1.0)], period=8.0)
    assert "limit" in (check_plan(proposal(too_fast), 0, cfg) or "")
    bad = SpinPlan(commands=[SpinCommand(omega=math.nan, duration=1.0)], period=8.0)
    assert "not executable" in (check_plan(proposal(bad), 0, cfg) or "")
    assert "stale" in (check_plan(proposal(ok, 0), 300_000_000, cfg) or "")
    assert check_plan(proposal(SpinPlan(commands=[]), 0), 0, cfg) is None  # nominal again


@given(angle_lists)
def test_every_planned_rotation_passes_legitimation(angles: list[float]) -> None:
    plan = SpinPlan(commands=commands_for(rotations(angles), 1.0))
    assert check_plan(proposal(plan), 0, LegitimacyConfig()) is None
