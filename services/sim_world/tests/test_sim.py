from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest
from rap_schemas import SpinCommand, SpinPlan, Twist
from sim_world.executor import PlanExecutor
from sim_world.sim import Simulation
from sim_world.world import default_world_path, load_world, parse_world

OPEN = """
seed: 1
room: {width: 20.0, height: 20.0}
robots: [{name: r, start: {x: 10.0, y: 10.0, theta: 0.0}}]
lidar: {rate_hz: 5.0}
"""


def trace_hash(sim: Simulation, seconds: float) -> str:
    h = hashlib.sha256()
    for ev in sim.run(seconds):
        h.update(ev.scan.ranges)  # packed float32
        p = sim.robots[ev.robot].pose
        h.update(np.array([ev.t, p.x, p.y, p.theta]).tobytes())
    return h.hexdigest()


def test_the_same_seed_gives_the_same_trace() -> None:
    world = load_world(default_world_path("default"))
    assert trace_hash(Simulation(world), 20.0) == trace_hash(Simulation(world), 20.0)
    other = parse_world(default_world_path("default").read_text().replace("seed: 7", "seed: 8"))
    assert trace_hash(Simulation(other), 20.0) != trace_hash(Simulation(world), 20.0)


def test_scans_come_at_the_lidar_rate_with_the_occluded_beams_at_inf() -> None:
    world = load_world(default_world_path("default"))
    sim = Simulation(world)
    events = sim.run(12.0)
    assert [round(e.t, 6) for e in events[:3]] == [0.2, 0.4, 0.6]  # every 0.2 s
    assert len(events) == 60
    for e in events:
        ranges = np.asarray(e.scan.values())
        assert np.isinf(ranges[e.occluded]).all()
        assert e.occluded.any() == (6.0 <= e.t < 36.0)
        assert e.scan.frame_id == "tb1/base_link"
        assert e.scan.stamp == round(e.t * 1e9)


def test_a_velocity_command_moves_the_robot_as_kinematics_says() -> None:
    sim = Simulation(parse_world(OPEN))
    sim.set_velocity("r", Twist(linear=0.2, angular=0.0), duration=5.0)
    sim.run(5.0)
    p = sim.robots["r"].pose
    # the drive joints take one physics step (0.02 s) to bring the body up to speed
    assert (p.x, p.y, p.theta) == pytest.approx((11.0, 10.0, 0.0), abs=0.2 * 0.02 + 1e-6)
    sim.set_velocity("r", Twist(linear=0.0, angular=1.0), duration=math.pi / 2)
    sim.run(math.pi / 2 - 1e-9)
    assert sim.robots["r"].pose.theta == pytest.approx(math.pi / 2, abs=0.03)


def test_driving_into_a_wall_counts_a_collision() -> None:
    world = parse_world(OPEN.replace("x: 10.0, y: 10.0", "x: 18.0, y: 10.0"))
    sim = Simulation(world)
    sim.set_velocity("r", Twist(linear=0.31, angular=0.0), duration=10.0)
    sim.run(10.0)
    r = sim.robots["r"]
    assert r.collisions >= 1
    assert r.pose.x <= 20.0 - r.spec.radius + 0.05  # the wall held


def test_the_executor_runs_commands_at_the_start_of_each_period() -> None:
    ex = PlanExecutor()
    ex.apply(
        SpinPlan(
            commands=[SpinCommand(omega=1.0, duration=1.5), SpinCommand(omega=-1.0, duration=1.0)],
            period=8.0,
        ),
        t=2.0,
    )
    samples = {t: ex.omega(t) for t in (1.9, 2.0, 3.4, 3.6, 4.4, 4.6, 9.9, 10.0, 11.6)}
    assert samples == {
        1.9: None,
        2.0: 1.0,
        3.4: 1.0,
        3.6: -1.0,
        4.4: -1.0,
        4.6: None,
        9.9: None,
        10.0: 1.0,
        11.6: -1.0,
    }
    ex.apply(SpinPlan(commands=[], period=8.0), t=12.0)  # an empty plan: nominal again
    assert ex.omega(12.5) is None


def test_a_plan_makes_the_simulated_robot_spin_then_drive_on() -> None:
    world = load_world(default_world_path("default"))
    sim = Simulation(world)
    sim.run(1.0)
    sim.set_plan("tb1", SpinPlan(commands=[SpinCommand(omega=1.0, duration=2.0)], period=8.0))
    start = sim.robots["tb1"].pose
    sim.run(1.99)
    spun = sim.robots["tb1"].pose
    assert math.hypot(spun.x - start.x, spun.y - start.y) < 0.02  # turning on the spot
    assert sim.robots["tb1"].w == pytest.approx(1.0)
    sim.run(1.0)
    assert sim.robots["tb1"].v > 0  # nominal navigation resumed


def test_a_robot_follows_its_route() -> None:
    world = load_world(default_world_path("obstacles_only"))
    sim = Simulation(world)
    sim.run(120.0)
    r = sim.robots["tb1"]
    assert r.nav.index == 3  # all three waypoints reached
    assert r.nav.done
