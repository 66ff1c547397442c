from __future__ import annotations

import math

import numpy as np
import pytest
from sim_world.kinematics import DiffDrive, Pose2, wrap
from sim_world.occlusion import GLOBAL_WINDOW, occlusion_mask
from sim_world.world import Arc, Occlusion, WorldError, parse_world

BEAMS = -math.pi + np.arange(360) * (2 * math.pi / 360)  # robot frame, 1 degree apart


def deg(mask: np.ndarray) -> set[int]:
    return {round(math.degrees(a)) for a in BEAMS[mask]}


def test_a_sector_covers_its_arc_only_while_active() -> None:
    occ = Occlusion(
        robot="r",
        mode="sector",
        start_angle=math.radians(10),
        width=math.radians(20),
        t_start=5,
        t_end=10,
    )
    assert not occlusion_mask([occ], "r", 4.9, BEAMS, 0).any()
    assert deg(occlusion_mask([occ], "r", 5.0, BEAMS, 0)) == set(range(10, 30))
    assert not occlusion_mask([occ], "r", 10.0, BEAMS, 0).any()
    assert not occlusion_mask([occ], "other", 7.0, BEAMS, 0).any()


def test_arcs_wrap_around_behind_the_robot() -> None:
    occ = Occlusion(
        robot="r",
        mode="arcs",
        arcs=[
            Arc(start_angle=math.radians(169.5), width=math.radians(20)),
            Arc(start_angle=math.radians(-90.5), width=math.radians(5)),
        ],
    )
    assert deg(occlusion_mask([occ], "r", 0, BEAMS, 0)) == (
        set(range(170, 180)) | set(range(-180, -170)) | set(range(-90, -85))
    )


def test_global_leaves_a_sixty_degree_window() -> None:
    occ = Occlusion(robot="r", mode="global", start_angle=0.0)
    visible = ~occlusion_mask([occ], "r", 0, BEAMS, 0)
    assert visible.sum() == round(math.degrees(GLOBAL_WINDOW))
    assert deg(visible) == set(range(-30, 30))


def test_random_arcs_are_seeded_change_each_period_and_stay_in_bounds() -> None:
    occ = Occlusion(robot="r", mode="random", period=2.0)
    masks = [occlusion_mask([occ], "r", t, BEAMS, seed=5) for t in (0.0, 1.9, 2.0, 4.0)]
    assert (masks[0] == masks[1]).all()  # the same period
    assert not (masks[1] == masks[2]).all()  # a new period, new arcs
    again = occlusion_mask([occ], "r", 2.0, BEAMS, seed=5)
    assert (again == masks[2]).all()  # reproducible
    for m in masks:
        assert 15 <= m.sum() <= 3 * 90 + 3


def test_straight_line_turn_on_the_spot_and_arc() -> None:
    tb4 = DiffDrive()
    p = tb4.step(Pose2(0, 0, 0), 0.2, 0.0, 2.0)
    assert (p.x, p.y, p.theta) == pytest.approx((0.4, 0.0, 0.0))
    p = tb4.step(Pose2(1, 1, 0), 0.0, 1.0, math.pi / 2)
    assert (p.x, p.y, p.theta) == pytest.approx((1.0, 1.0, math.pi / 2))
    # a quarter circle of radius v / w = 0.2 m, counter-clockwise
    p = tb4.step(Pose2(0, 0, 0), 0.2, 1.0, math.pi / 2)
    assert (p.x, p.y, p.theta) == pytest.approx((0.2, 0.2, math.pi / 2))
    # many small steps land where one exact step does
    q = Pose2(0, 0, 0)
    for _ in range(1000):
        q = tb4.step(q, 0.25, -0.7, 0.005)
    r = tb4.step(Pose2(0, 0, 0), 0.25, -0.7, 5.0)
    assert (q.x, q.y, q.theta) == pytest.approx((r.x, r.y, r.theta), abs=1e-9)


def test_limits_are_those_of_a_turtlebot_4() -> None:
    tb4 = DiffDrive()
    assert tb4.clamp(1.0, -5.0) == (0.31, -1.9)
    p = tb4.step(Pose2(0, 0, 0), 10.0, 0.0, 1.0)
    assert p.x == pytest.approx(0.31)
    left, right = tb4.wheels(0.0, 1.0)
    assert (left, right) == pytest.approx((-0.1165, 0.1165))
    assert wrap(3 * math.pi) == pytest.approx(math.pi)


GOOD = "robots: [{name: r, start: {x: 1.0, y: 1.0}}]\n"


@pytest.mark.parametrize(
    ("text", "where", "words"),
    [
        ("robots:\n  - name: r\n    start: {x: one, y: 1.0}\n", "w.yaml:3:", "$.robots[0].start.x"),
        ("room: {width: -1}\n" + GOOD, "w.yaml:1:", "Expected `float` > 0.0"),
        ("robots:\n  - {name: r, strat: {x: 1, y: 1}}\n", "w.yaml:2:", "unknown field `strat`"),
        (
            "robots:\n  - {name: r, start: {x: 1, y: 1}}\n  - {name: r, start: {x: 2, y: 2}}\n",
            "w.yaml:3:",
            "used twice",
        ),
        (
            GOOD + "occlusions: [{robot: nobody, mode: sector, width: 1}]\n",
            "w.yaml:2:",
            "names robot 'nobody'",
        ),
        (
            GOOD + "occlusions: [{robot: r, mode: sector, width: 1, t_start: 5, t_end: 2}]\n",
            "w.yaml:2:",
            "ends (t_end=2.0) before it starts",
        ),
        ("robots: [\n", "w.yaml:2:", "not valid YAML"),
        ("", "w.yaml", "empty"),
        ("obstacles: [{kind: triangle, x: 1}]\n" + GOOD, "w.yaml:1:", "Invalid value 'triangle'"),
    ],
)
def test_bad_world_files_name_the_line_and_the_fix(text: str, where: str, words: str) -> None:
    with pytest.raises(WorldError) as exc:
        parse_world(text, "w.yaml")
    assert str(exc.value).startswith(where), str(exc.value)
    assert words in str(exc.value)
