"""The belief map and the digital twin: what the robot knows, and plans rolled out on it."""

from __future__ import annotations

import ast
import math
import re
from pathlib import Path

import anyio
import msgspec
import numpy as np
import numpy.typing as npt
import pytest
from lidar_occlusion.belief import LidarBelief, MapConfig, ObstacleMap, belief_of, update
from lidar_occlusion.planning import PlanConfig, plan_for
from lidar_occlusion.twin import LidarTwin, TwinConfig, limits, pose_mismatch, robot_state_spec
from rap_schemas import LaserScan, LidarMask, Pose2D, SpinCommand, SpinPlan, pack_flags, pack_ranges
from rap_schemas.catalog import by_type
from rap_sdk.twin import TwinKind, ask
from sim_world.geometry import Scene, cast_rays, scene_of
from sim_world.sim import Simulation
from sim_world.world import Circle, Pose, RobotSpec, Room, WorldSpec, default_world_path, load_world

N = 360
INC = 2 * math.pi / N
BEAMS = -math.pi + np.arange(N) * INC  # robot frame
FULL_TURN = SpinPlan(commands=[SpinCommand(omega=1.0, duration=2 * math.pi)], period=8.0)
NOMINAL = SpinPlan(commands=[], period=8.0)


def world(*obstacles: Circle) -> WorldSpec:
    return WorldSpec(
        room=Room(width=10.0, height=8.0),
        obstacles=list(obstacles),
        robots=[RobotSpec(name="tb1", start=Pose(x=1.0, y=4.0))],
    )


def occluded(start: float, width: float) -> npt.NDArray[np.bool_]:
    """Robot-frame beams within ``width`` rad counter-clockwise of ``start``."""
    return np.mod(BEAMS - start, 2 * math.pi) < width


def scan_of(
    scene: Scene, pose: Pose2D, hidden: npt.NDArray[np.bool_] | None = None, stamp: float = 0.0
) -> LaserScan:
    """What a 360-beam lidar at ``pose`` sees of ``scene`` (``hidden`` beams read inf)."""
    r = cast_rays(pose.x, pose.y, pose.theta + BEAMS, scene, 12.0)
    if hidden is not None:
        r[hidden] = np.inf
    return LaserScan(
        stamp=round(stamp * 1e9),
        frame_id="tb1/base_link",
        angle_min=-math.pi,
        angle_increment=INC,
        range_min=0.1,
        range_max=12.0,
        ranges=pack_ranges(r),
    )


def mask_of(hidden: npt.NDArray[np.bool_]) -> LidarMask:
    return LidarMask(angle_min=-math.pi, angle_increment=INC, occluded=pack_flags(hidden))


def belief(
    m: ObstacleMap,
    pose: Pose2D,
    route: list[tuple[float, float]],
    mask: LidarMask | None = None,
    t: float | None = None,
) -> LidarBelief:
    return LidarBelief(
        robot="tb1", pose=pose, map=m, mask=mask, route=route, t=m.t if t is None else t
    )


def blank(pose: Pose2D, stamp: float) -> LaserScan:
    """A scan with no return at all (every beam occluded)."""
    return scan_of(Scene(np.zeros((0, 4)), np.zeros((0, 3))), pose, np.ones(N, bool), stamp)


HERE = Pose2D(x=1.0, y=4.0, theta=0.0)
ROUTE = [(8.0, 4.0)]


# -- the map -------------------------------------------------------------------------------


def test_cells_land_where_the_returns_do_and_decay_after_their_ttl() -> None:
    cfg = MapConfig(ttl_s=10.0)
    scene = scene_of(world(Circle(x=2.0, y=4.0, r=0.3)))
    m = update(None, scan_of(scene, HERE), HERE, 0.0, cfg)
    pts = m.obstacles()
    assert m.size > 0
    # every cell centre lies within half a cell's diagonal of the circle's surface or of
    # a wall within max_range
    on_circle = np.abs(np.hypot(pts[:, 0] - 2.0, pts[:, 1] - 4.0) - 0.3) <= cfg.cell
    on_wall = (pts[:, 0] <= cfg.cell) | (pts[:, 1] <= cfg.cell) | (pts[:, 1] >= 8.0 - cfg.cell)
    assert np.all(on_circle | on_wall)
    assert on_circle.sum() >= 10
    # no return from anywhere farther than max_range
    assert np.hypot(pts[:, 0] - HERE.x, pts[:, 1] - HERE.y).max() <= cfg.max_range + cfg.cell

    later = update(m, blank(HERE, 9.0), HERE, 9.0, cfg)
    assert later.size == m.size  # not seen for 9 s: kept
    assert later.seen_ages().min() == pytest.approx(9.0)
    gone = update(later, blank(HERE, 10.5), HERE, 10.5, cfg)
    assert gone.size == 0
    assert len(gone.looked) == 0
    assert m.size > 0  # update is pure: the old map is as it was


def test_a_cell_seen_again_is_refreshed() -> None:
    cfg = MapConfig(ttl_s=5.0)
    scene = scene_of(world(Circle(x=2.0, y=4.0, r=0.3)))
    m = update(None, scan_of(scene, HERE), HERE, 0.0, cfg)
    for t in (4.0, 8.0, 12.0):
        m = update(m, scan_of(scene, HERE, stamp=t), HERE, t, cfg)
    assert m.size > 0
    assert m.seen_ages().max() == pytest.approx(0.0)


def test_the_map_stays_bounded_keeping_the_newest_cells() -> None:
    cfg = MapConfig(max_cells=200, max_looked=60, ttl_s=100.0)
    m = None
    for i in range(30):  # the robot drives along; each scan adds cells
        pose = Pose2D(x=0.5 + 0.3 * i, y=4.0, theta=0.0)
        obstacle = Circle(x=0.5 + 0.3 * i, y=2.5, r=0.2)
        m = update(m, scan_of(scene_of(world(obstacle)), pose), pose, float(i), cfg)
        assert m.size <= 200
        assert len(m.looked) // 8 <= 60
    assert m is not None
    assert m.size == 200
    ages = m.seen_ages()
    newest = update(None, scan_of(scene_of(world(obstacle)), pose), pose, 29.0, cfg)
    kept = set(m.keys().tolist())
    assert set(newest.keys().tolist()) <= kept  # the last scan's cells all stayed
    assert ages.max() < 29.0  # the oldest went first
    # sorted keys: lookups by binary search hold
    keys = m.keys()
    assert np.all(keys[1:] > keys[:-1])


def test_occluded_beams_add_nothing_and_count_as_not_looked_at() -> None:
    cfg = MapConfig()
    scene = scene_of(world(Circle(x=2.0, y=4.0, r=0.3), Circle(x=1.0, y=5.2, r=0.3)))
    front = occluded(-0.6, 1.2)  # hides the circle ahead, not the one to the left
    m = update(None, scan_of(scene, HERE, front), HERE, 0.0, cfg)
    pts = m.obstacles()
    assert not np.any(np.hypot(pts[:, 0] - 2.0, pts[:, 1] - 4.0) < 0.5)  # hidden: not mapped
    assert np.any(np.hypot(pts[:, 0] - 1.0, pts[:, 1] - 5.2) < 0.5)  # seen: mapped
    assert not m.seen_recently(0.0, 0.2, 0.0, 5.0)  # straight ahead: not looked along
    assert m.seen_recently(math.pi / 2, 0.2, 0.0, 5.0)  # to the left: looked along
    assert not m.seen_recently(math.pi / 2, 0.2, 6.0, 5.0)  # ... but not within 5 s of t=6
    ahead = m.looked_recently([(1.6, 4.0), (1.0, 4.5)], 0.0, 5.0)
    assert ahead.tolist() == [False, True]
    nothing = update(None, blank(HERE, 0.0), HERE, 0.0, cfg)
    assert nothing.size == 0
    assert not nothing.looked
    assert not nothing.seen_recently(0.0, math.pi, 0.0, 100.0)


def test_cells_seen_from_near_are_what_navigation_remembers() -> None:
    cfg = MapConfig()
    scene = scene_of(world(Circle(x=4.0, y=4.0, r=0.3)))
    far = Pose2D(x=0.5, y=4.0, theta=0.0)  # the circle 3.2 m away: mapped, not near
    m = update(None, scan_of(scene, far), far, 0.0, cfg)
    pts = m.obstacles()
    circle = np.hypot(pts[:, 0] - 4.0, pts[:, 1] - 4.0) < 0.5
    assert circle.any()
    assert np.all(np.isinf(m.near_ages()[circle]))
    near = Pose2D(x=2.0, y=4.0, theta=0.0)
    seen_near = set(update(None, scan_of(scene, near), near, 3.0, cfg).keys().tolist())
    m = update(m, scan_of(scene, near), near, 3.0, cfg)
    ages = dict(zip(m.keys().tolist(), m.near_ages().tolist(), strict=True))
    pts = m.obstacles()
    on_circle = [
        k for k, p in zip(m.keys().tolist(), pts, strict=True) if math.dist(p, (4, 4)) < 0.5
    ]
    assert any(k in seen_near for k in on_circle)
    for k in on_circle:  # seen from 1.7 m now: near; the rest still never
        assert ages[k] == (0.0 if k in seen_near else math.inf)


def test_the_map_and_the_belief_go_through_knowledge_encoding() -> None:
    scene = scene_of(world(Circle(x=2.0, y=4.0, r=0.3)))
    m = update(None, scan_of(scene, HERE, stamp=3.0), HERE, 3.0, MapConfig())
    b = belief(m, HERE, ROUTE, mask_of(occluded(-0.5, 1.0)))
    raw = msgspec.msgpack.encode(b)
    assert len(raw) < 64 * 1024
    back = msgspec.msgpack.decode(raw, type=LidarBelief)
    assert back == b
    assert by_type("lidar_occlusion.LidarBelief/1") is LidarBelief
    assert by_type("lidar_occlusion.ObstacleMap/1") is ObstacleMap
    broken = msgspec.structs.asdict(m) | {"seen_age": b""}
    with pytest.raises(msgspec.ValidationError, match="do not match"):
        msgspec.msgpack.decode(msgspec.msgpack.encode(broken), type=ObstacleMap)


def test_configs_name_the_bad_field() -> None:
    with pytest.raises(ValueError, match=r"MapConfig\.cell"):
        MapConfig(cell=0.0)
    with pytest.raises(ValueError, match=r"MapConfig\.max_cells"):
        MapConfig(max_cells=0)
    with pytest.raises(ValueError, match=r"TwinConfig\.step"):
        TwinConfig(step=math.nan)
    with pytest.raises(ValueError, match=r"TwinConfig\.scan_hz"):
        TwinConfig(step=0.5, scan_hz=5.0)
    with pytest.raises(ValueError, match=r"update: pose"):
        update(None, blank(HERE, 0.0), Pose2D(x=math.nan, y=0.0, theta=0.0), 0.0, MapConfig())


# -- the twin ------------------------------------------------------------------------------


def mapped(scene: Scene, *views: tuple[Pose2D, float, npt.NDArray[np.bool_] | None]) -> ObstacleMap:
    m = None
    for pose, t, hidden in views:
        m = update(m, scan_of(scene, pose, hidden, t), pose, t, MapConfig())
    assert m is not None
    return m


def test_a_safe_plan_in_open_space_is_approved() -> None:
    scene = scene_of(world())
    here = Pose2D(x=5.0, y=4.0, theta=0.0)
    b = belief(mapped(scene, (here, 0.0, None)), here, [(6.5, 4.0)])
    twin = LidarTwin()
    assert twin.kind is TwinKind.SIMULATION
    report = twin.rollout(FULL_TURN, b)
    assert report.verdict is None, report.findings
    assert report.findings == []
    assert not report.belief.thin
    assert report.horizon_s == 8.0
    assert report.metrics["spin_s"] == pytest.approx(2 * math.pi, abs=0.11)
    assert report.metrics["collisions"] == 0
    assert report.metrics["min_clearance_m"] == 1.0  # nothing within the cap
    # straight on toward the waypoint at top speed for the 1.7 s left after the turn
    assert report.metrics["progress_m"] == pytest.approx((8.0 - 2 * math.pi) * 0.31, abs=0.04)
    assert report.metrics["end_y_m"] == pytest.approx(4.0, abs=0.01)


def hidden_obstacle() -> tuple[Scene, LidarBelief]:
    """An obstacle ahead, mapped from 3 m away (too far for navigation to remember it),
    then hidden by an occlusion of the front sector."""
    scene = scene_of(world(Circle(x=3.6, y=4.0, r=0.3)))
    front = occluded(-0.7, 1.4)
    back = Pose2D(x=0.5, y=4.0, theta=0.0)
    m = mapped(scene, (back, 0.0, None), (HERE, 1.6, front))
    return scene, belief(m, HERE, ROUTE, mask_of(front))


def test_nominal_navigation_into_a_believed_obstacle_hidden_by_the_mask_is_a_collision() -> None:
    _, b = hidden_obstacle()
    report = LidarTwin().rollout(NOMINAL, b)
    assert report.verdict is not None
    assert report.verdict.startswith("collision: ")
    hit = report.rejections[0]
    assert hit.at_s is not None
    assert 5.0 < hit.at_s < 8.0
    where = re.search(r"obstacle at \(([\d.]+), ([\d.]+)\)", hit.message)
    assert where is not None  # where: on the circle's near side
    assert math.dist((float(where[1]), float(where[2])), (3.6, 4.0)) == pytest.approx(0.3, abs=0.05)
    assert report.metrics["collisions"] == 1
    assert report.metrics["min_clearance_m"] < 0
    # the robot-state spec saw it too
    assert "spec:clearance_ok" in [f.code for f in report.findings]


def test_a_spin_that_looks_at_the_hidden_obstacle_avoids_it() -> None:
    _, b = hidden_obstacle()
    twin = LidarTwin()
    report = twin.rollout(FULL_TURN, b)
    assert report.rejections == [], report.findings
    assert report.metrics["collisions"] == 0
    assert report.metrics["min_clearance_m"] >= TwinConfig().min_clearance
    # the case's own planner, on the same mask, gives a plan the twin approves as well
    assert b.mask is not None
    plan = plan_for(
        np.asarray(b.mask.flags()), b.mask.angle_min, b.mask.angle_increment, PlanConfig()
    )
    assert plan.commands
    assert twin.rollout(plan, b).verdict is None


def test_without_the_mask_navigation_sees_the_obstacle_and_no_spin_is_needed() -> None:
    _, b = hidden_obstacle()
    report = LidarTwin().rollout(NOMINAL, msgspec.structs.replace(b, mask=None))
    assert report.verdict is None, report.findings


@pytest.mark.parametrize(
    ("plan", "what"),
    [
        (SpinPlan(commands=[SpinCommand(omega=3.0, duration=1.0)]), "beyond the robot's limit"),
        (SpinPlan(commands=[SpinCommand(omega=1.0, duration=8.5)]), "not within the period"),
        (SpinPlan(commands=[SpinCommand(omega=1.0, duration=1.0)], period=60.0), "longest"),
    ],
)
def test_plans_beyond_the_limits_are_rejected(plan: SpinPlan, what: str) -> None:
    scene = scene_of(world())
    here = Pose2D(x=5.0, y=4.0, theta=0.0)
    report = LidarTwin().rollout(plan, belief(mapped(scene, (here, 0.0, None)), here, [(6.5, 4.0)]))
    assert report.verdict is not None
    assert report.verdict.startswith("limits: ")
    assert what in report.verdict
    assert report.horizon_s > 0  # still rolled out: the metrics say what it would do


def test_a_too_fast_spin_also_breaks_the_robot_state_spec() -> None:
    here = Pose2D(x=5.0, y=4.0, theta=0.0)
    b = belief(mapped(scene_of(world()), (here, 0.0, None)), here, [(6.5, 4.0)])
    plan = SpinPlan(commands=[SpinCommand(omega=-2.5, duration=1.0)])
    codes = [f.code for f in LidarTwin().rollout(plan, b).rejections]
    assert codes == ["limits", "spec:turn_ok"]
    quiet = LidarTwin(TwinConfig(trust=False)).rollout(plan, b)
    assert [f.code for f in quiet.rejections] == ["limits"]


@pytest.mark.parametrize(
    "plan",
    [
        SpinPlan(commands=[SpinCommand(omega=math.nan, duration=1.0)]),
        SpinPlan(commands=[SpinCommand(omega=1.0, duration=-1.0)]),
        SpinPlan(commands=[], period=math.inf),
    ],
)
def test_a_plan_that_cannot_be_executed_is_not_rolled_out(plan: SpinPlan) -> None:
    findings, executable = limits(plan, TwinConfig())
    assert not executable
    assert [f.code for f in findings] == ["limits"]
    here = Pose2D(x=5.0, y=4.0, theta=0.0)
    report = LidarTwin().rollout(plan, belief(ObstacleMap(), here, []))
    assert report.horizon_s == 0
    assert report.verdict is not None
    assert report.verdict.startswith("limits: ")


def test_a_belief_that_is_not_finite_approves_nothing() -> None:
    b = belief(ObstacleMap(), Pose2D(x=5.0, y=4.0, theta=0.0), [(6.5, 4.0)])
    report = LidarTwin().rollout(NOMINAL, msgspec.structs.replace(b, v=math.nan))
    assert report.verdict is not None
    assert report.verdict.startswith("belief: ")
    assert report.horizon_s == 0


def test_a_plan_for_another_robot_or_another_pose_is_flagged() -> None:
    here = Pose2D(x=1.0, y=1.0, theta=0.2)
    assert pose_mismatch(here, here, "tb1", "tb1") is None
    close = Pose2D(x=1.05, y=1.02, theta=0.3)
    assert pose_mismatch(here, close, "tb1", "tb1") is None
    other = pose_mismatch(here, here, "tb1", "tb2")
    assert other is not None
    assert other.code == "pose-mismatch"
    assert "'tb2'" in other.message
    far = pose_mismatch(here, Pose2D(x=1.6, y=1.0, theta=0.2), "tb1", "tb1")
    assert far is not None
    assert far.severity == "reject"
    assert "0.60 m" in far.message
    turned = pose_mismatch(here, Pose2D(x=1.0, y=1.0, theta=-2.9), "tb1", "tb1")
    assert turned is not None  # 3.1 rad the short way round (wrapped)
    tight = TwinConfig(max_shift=0.01)
    assert pose_mismatch(here, close, "tb1", "tb1", tight) is not None


def test_thin_belief_is_reported_when_the_way_ahead_was_never_looked_at() -> None:
    scene = scene_of(world())
    here = Pose2D(x=5.0, y=4.0, theta=0.0)
    front = occluded(-1.2, 2.4)
    b = belief(mapped(scene, (here, 0.0, front)), here, [(7.0, 4.0)], mask_of(front))
    report = LidarTwin().rollout(NOMINAL, b)
    assert report.belief.thin
    assert [(f.code, f.severity) for f in report.findings] == [("thin-belief", "note")]
    assert report.verdict is None  # a note: the twin found nothing, and says how little it knew
    assert "not looked at" in report.belief.notes[0]
    # looked at in full (no occlusion), the same way ahead is not thin
    seen = belief(mapped(scene, (here, 0.0, None)), here, [(7.0, 4.0)])
    assert not LidarTwin().rollout(NOMINAL, seen).belief.thin
    # ... until that look is older than thin_within
    stale = msgspec.structs.replace(seen, t=11.0)
    assert LidarTwin(TwinConfig(thin_within=10.0)).rollout(NOMINAL, stale).belief.thin


def test_the_twin_follows_the_belief_not_the_world() -> None:
    """A world with an obstacle on the route, a belief mapped from a world without it:
    the twin drives straight through where the obstacle really is. A phantom obstacle
    in the belief, in no world, is one the twin avoids or hits."""
    real = world(Circle(x=3.0, y=4.0, r=0.3))
    sim = Simulation(real)  # the simulator's world holds the obstacle
    assert sim.world.obstacles
    empty = scene_of(world())
    b = belief(mapped(empty, (HERE, 0.0, None)), HERE, ROUTE)
    report = LidarTwin().rollout(NOMINAL, b)
    assert report.verdict is None
    assert report.metrics["progress_m"] > 2.3  # straight on, past x = 3.0
    phantom = belief(mapped(empty, (HERE, 0.0, None)), HERE, ROUTE, mask_of(occluded(-0.7, 1.4)))
    ghost = scene_of(world(Circle(x=2.5, y=4.0, r=0.3)))
    phantom = msgspec.structs.replace(phantom, map=mapped(ghost, (HERE, 0.0, None)))
    assert LidarTwin().rollout(NOMINAL, phantom).metrics["min_clearance_m"] < 1.0
    # and by construction: the twin's modules never load a world nor the simulator
    src = Path(__file__).parents[1] / "src" / "lidar_occlusion"
    for name in ("twin.py", "belief.py"):
        tree = ast.parse((src / name).read_text(encoding="utf-8"))
        imported = {
            (n.module, a.name)
            for n in ast.walk(tree)
            if isinstance(n, ast.ImportFrom) and n.module
            for a in n.names
        }
        banned = {m for m, _ in imported} & {
            "sim_world.sim",
            "sim_world.geometry",
            "sim_world.physics",
        }
        assert not banned, (name, banned)
        assert not {a for _, a in imported} & {
            "load_world",
            "find_world",
            "Simulation",
            "cast_rays",
        }


@pytest.mark.parametrize("name", ["default", "obstacles_only"])
def test_with_a_complete_belief_the_twin_predicts_the_simulator(name: str) -> None:
    """Mapped from the simulator's own scans, without occlusion in force, the twin's 8 s
    of nominal navigation ends within a few centimetres of where the simulator does."""
    w = load_world(default_world_path(name))
    w = msgspec.structs.replace(w, occlusions=[])
    sim = Simulation(w)
    route = [(p.x, p.y) for p in w.robots[0].route]
    m = None
    last = None
    for _ in range(round(12.0 / sim.dt)):
        for ev in sim.step():
            odom = sim.odometry("tb1")
            m = update(m, ev.scan, odom.pose, ev.t, MapConfig())
            last = ev
    assert m is not None
    assert last is not None
    b = belief_of("tb1", odom, last.scan, m, None, route, waypoint=sim.robots["tb1"].nav.index)
    report = LidarTwin().rollout(NOMINAL, b)
    sim.run(8.0)
    real = sim.robots["tb1"].pose
    assert report.metrics["progress_m"] > 1.0  # it did drive
    end = report.metrics["end_x_m"], report.metrics["end_y_m"]
    assert math.hypot(end[0] - real.x, end[1] - real.y) < 0.1


def test_ask_runs_the_twin_off_the_event_loop() -> None:
    scene = scene_of(world())
    here = Pose2D(x=5.0, y=4.0, theta=0.0)
    b = belief(mapped(scene, (here, 0.0, None)), here, [(6.5, 4.0)])

    async def main() -> float:
        report = await ask(LidarTwin(), FULL_TURN, b)
        assert report.verdict is None
        return report.elapsed_s

    assert anyio.run(main) > 0


def test_the_shipped_spec_has_the_twin_config_defaults() -> None:
    text = robot_state_spec()
    cfg = TwinConfig()
    assert f"clearance >= {cfg.min_clearance}" in text
    assert f"abs(omega) <= {cfg.max_angular}" in text
