"""The ship model behaves like a ship: straight, turning, bounded, deterministic, weathered."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from ship_motion.physics import (
    Disturbance,
    History,
    Route,
    RouteFollower,
    ScenarioSpec,
    ShipCommand,
    ShipParams,
    ShipSimulator,
    ShipState,
    Waypoint,
    scenario_from_seed,
    simulate,
)

CALM_START = ShipState(t=0.0, x=0.0, y=0.0, psi=0.0, u=5.5, v=0.0, r=0.0, rps=3.0)


def held(rudder_deg: float, rps: float = 3.0) -> ShipCommand:
    return ShipCommand(rudder=math.radians(rudder_deg), rps=rps)


def run_held(command: ShipCommand, seconds: float, **spec: object) -> History:
    scenario = msgspec.structs.replace(ScenarioSpec(duration_s=seconds, start=CALM_START), **spec)
    return simulate(scenario, controller=lambda _state, _dt: command)


def test_zero_rudder_sails_a_straight_line_at_cruising_speed() -> None:
    start = msgspec.structs.replace(CALM_START, psi=0.7)
    h = simulate(ScenarioSpec(duration_s=300.0, start=start), controller=lambda _s, _dt: held(0.0))
    assert np.allclose(h.column("psi"), 0.7, atol=1e-12)
    assert np.allclose(h.column("r"), 0.0, atol=1e-12)
    assert np.allclose(h.column("v"), 0.0, atol=1e-12)
    # every position lies on the line through the start along the heading
    cross = -h.column("x") * math.sin(0.7) + h.column("y") * math.cos(0.7)
    assert np.abs(cross).max() < 1e-6
    # the speed settles where thrust meets resistance: about 5.8 m/s at 3 rps
    assert h.column("u")[-1] == pytest.approx(5.78, abs=0.05)


def test_rudder_sign_sets_the_turning_direction_and_the_circle_is_mirrored() -> None:
    starboard = run_held(held(20.0), 300.0)
    port = run_held(held(-20.0), 300.0)
    # heading north, a starboard turn goes east (y > 0) with psi growing
    assert starboard.column("r")[-1] > 0.02
    assert starboard.column("y")[30] > 0 > port.column("y")[30]
    assert np.allclose(starboard.column("x"), port.column("x"), atol=1e-9)
    assert np.allclose(starboard.column("y"), -port.column("y"), atol=1e-9)
    # a steady turn: a circle of a few ship lengths, run at reduced speed
    late = starboard.between(150.0)
    x, y = late.column("x"), late.column("y")
    # the circle through the late positions, fitted by least squares: x^2 + y^2 = a x + b y + c
    (a, b, _c), *_ = np.linalg.lstsq(np.stack([x, y, np.ones_like(x)], axis=1), x**2 + y**2)
    centre = (a / 2, b / 2)
    radius = np.hypot(x - centre[0], y - centre[1])
    assert 2 * 40.0 < radius.mean() < 10 * 40.0
    assert radius.std() < 0.01 * radius.mean()
    assert centre[1] > 0  # the centre lies to starboard of the first course (north)
    assert late.column("u").max() < starboard.column("u")[0]


def test_speed_and_energy_stay_bounded_under_hard_manoeuvres() -> None:
    params = ShipParams()

    def zigzag(state: ShipState, _dt: float) -> ShipCommand:
        side = 1.0 if int(state.t // 40) % 2 == 0 else -1.0
        return ShipCommand(rudder=side * params.rudder_max, rps=params.rps_max)

    h = simulate(ScenarioSpec(duration_s=900.0, start=CALM_START), controller=zigzag)
    speed = np.hypot(h.column("u"), h.column("v"))
    # the straight-line top speed at full revolutions is under 10 m/s; turning only costs speed
    assert speed.max() < 10.0
    assert np.abs(h.column("r")).max() < 0.2
    assert np.abs(h.column("rudder")).max() <= params.rudder_max + 1e-12
    energy = 0.5 * params.mass * speed**2 + 0.5 * params.inertia * h.column("r") ** 2
    assert energy.max() < 0.5 * params.mass * 10.0**2


def test_a_run_is_a_pure_function_of_its_spec() -> None:
    spec = scenario_from_seed(3, onset_s=100.0, duration_s=300.0)
    first = simulate(spec)
    again = simulate(msgspec.json.decode(msgspec.json.encode(spec), type=ScenarioSpec))
    assert np.array_equal(first.data, again.data)
    other = simulate(scenario_from_seed(4, onset_s=100.0, duration_s=300.0))
    assert not np.array_equal(first.data, other.data)
    assert scenario_from_seed(3).disturbances != scenario_from_seed(4).disturbances


def test_the_weather_changes_the_dynamics() -> None:
    calm = ScenarioSpec(duration_s=600.0, start=CALM_START)
    windy = msgspec.structs.replace(
        calm,
        disturbances=[
            Disturbance(kind="wind", onset_s=100.0, ramp_s=30.0, magnitude=16.0, direction=1.2),
            Disturbance(kind="current", onset_s=100.0, ramp_s=30.0, magnitude=1.0, direction=2.0),
            Disturbance(kind="waves", onset_s=100.0, ramp_s=30.0, magnitude=2.5, direction=1.5),
        ],
    )
    straight = held(0.0)
    a = simulate(calm, controller=lambda _s, _dt: straight)
    b = simulate(windy, controller=lambda _s, _dt: straight)
    before, after = a.t <= 100.0, a.t > 100.0
    assert np.array_equal(a.data[before], b.data[before])
    # with the rudder amidships the calm ship keeps its heading; in the weather it turns and
    # drifts, and the same command takes it somewhere else
    assert np.abs(a.column("r")).max() < 1e-12
    assert np.abs(b.column("r")[after]).max() > 1e-3
    gap = np.hypot(a.column("x") - b.column("x"), a.column("y") - b.column("y"))
    assert gap[-1] > 100.0

    sim = ShipSimulator(windy)
    for _ in range(1500):
        sim.step(straight)
    weather = sim.weather()
    assert weather.wind_speed == pytest.approx(16.0)
    assert weather.current_speed == pytest.approx(1.0)
    assert weather.wave_height == pytest.approx(2.5)
    assert weather.wind_direction == pytest.approx(1.2)


def test_the_route_follower_sails_the_route_in_calm_and_in_weather() -> None:
    for spec in (
        ScenarioSpec(duration_s=1200.0),
        scenario_from_seed(5, onset_s=0.0, duration_s=1200.0),
    ):
        follower = RouteFollower(spec.route)
        h = simulate(spec, follower=follower)
        assert follower.leg >= 6  # round the hexagon at least once
        points = [(w.x, w.y) for w in spec.route.waypoints]
        legs = list(zip(points, points[1:] + points[:1], strict=True))
        off = np.array([_distance_to_route(x, y, legs) for x, y in h.data[:, 1:3]])
        # off the legs only where it cuts a corner at the wheel-over point
        assert np.median(off) < 25.0
        assert off.max() < 100.0


def _distance_to_route(
    x: float, y: float, legs: list[tuple[tuple[float, float], tuple[float, float]]]
) -> float:
    best = math.inf
    for (ax, ay), (bx, by) in legs:
        dx, dy = bx - ax, by - ay
        k = min(max(((x - ax) * dx + (y - ay) * dy) / (dx * dx + dy * dy), 0.0), 1.0)
        best = min(best, math.hypot(x - ax - k * dx, y - ay - k * dy))
    return best


def test_non_finite_and_out_of_range_values_are_refused_with_a_reason() -> None:
    with pytest.raises(ValueError, match=r"ShipCommand\.rudder is nan"):
        ShipCommand(rudder=math.nan, rps=3.0)
    with pytest.raises(msgspec.ValidationError, match="rps is inf"):
        msgspec.convert({"rudder": 0.0, "rps": math.inf}, ShipCommand)
    with pytest.raises(msgspec.ValidationError, match="Number out of range"):
        msgspec.json.decode(b'{"rudder": 0.0, "rps": 1e400}', type=ShipCommand)
    with pytest.raises(ValueError, match="magnitude of wind"):
        Disturbance(kind="wind", onset_s=0.0, ramp_s=0.0, magnitude=-1.0, direction=0.0)
    with pytest.raises(ValueError, match="onset_s"):
        Disturbance(kind="waves", onset_s=-5.0, ramp_s=0.0, magnitude=1.0, direction=0.0)
    with pytest.raises(ValueError, match="whole number of steps"):
        ScenarioSpec(dt=0.3, sample_period=1.0)
    with pytest.raises(ValueError, match="at least two waypoints"):
        Route(waypoints=[Waypoint(0.0, 0.0)])
    with pytest.raises(ValueError, match="mass is 0"):
        ShipParams(mass=0.0)
    with pytest.raises(ValueError, match="non-finite"):
        History([[0.0, math.nan, 0, 0, 0, 0, 0, 0, 0]])
