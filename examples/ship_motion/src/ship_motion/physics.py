"""The managed system of the case: a ship that sails a route while the weather pushes it.

The model is a 3-DOF manoeuvring model in the horizontal plane, of the family written in
vectorial form by Fossen (*Handbook of Marine Craft Hydrodynamics and Motion Control*) with
the forces split the way the Japanese MMG models split them (Yasukawa and Yoshimura, 2015):
hull, propeller and rudder each contribute, and the weather adds its own forces.

Frames and signs: the earth frame is north-east-down, so ``x`` points north, ``y`` east and
the heading ``psi`` turns clockwise from north. The body frame has ``u`` forward and ``v`` to
starboard; ``r`` is the yaw rate. A positive rudder angle turns the ship to starboard
(``r > 0``, ``psi`` growing).

What the model keeps (per unit of the body frame, ``m`` the mass, ``m_x``, ``m_y``, ``J_z`` the
added mass and inertia, ``u_r``, ``v_r`` the velocity through the water)::

    (m + m_x) du_r/dt = (m + m_y) v_r r + X_hull + X_prop + X_rudder + X_weather
    (m + m_y) dv_r/dt = -(m + m_x) u_r r + Y_hull + Y_rudder + Y_weather
    (I_z + J_z) dr/dt = N_hull + N_rudder + N_weather

- hull: linear and quadratic damping in surge; in sway and yaw a damping that grows with the
  speed (the usual linear manoeuvring derivatives are proportional to it) plus a quadratic
  cross-flow term. The destabilising Munk moment is left out, so the bare hull is
  directionally stable and a Nomoto first-order model describes its yaw response well.
- propeller: thrust ``a n|n| - b n u_r`` (a linear open-water curve, thrust deduction folded
  into ``a`` and ``b``), ``n`` in revolutions per second behind a first-order lag.
- rudder: a normal force ``c U_R^2 sin(delta)`` with the inflow ``U_R^2 = u_r^2 + k n^2``
  (the slipstream keeps steerage at low speed); it pushes the stern sideways at the rudder's
  lever arm and costs some drag. The rudder turns at a limited rate up to a limited angle.
- weather: wind as a drag on the ship's above-water areas from the wind relative to the
  ship; waves as a mean second-order drift force and moment scaled by the significant wave
  height squared, plus a first-order oscillation at the wave period; current by moving the
  water: the hull forces see the velocity through the water, the pose moves over ground.

Each disturbance has an onset, a linear ramp, a magnitude and a direction, drawn from a seed
by :func:`scenario_from_seed` or written out. Integration is fourth-order Runge-Kutta at a
fixed step, with the weather's force held over each step, so a run is a pure function of its
:class:`ScenarioSpec`.

A :class:`RouteFollower` (line-of-sight guidance with crab-angle compensation and a PID
heading autopilot) gives the rudder so that the ship sails its route, round and round.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Literal, TypeAlias

import msgspec
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "COLUMNS",
    "DISTURBANCE_LIMITS",
    "Disturbance",
    "History",
    "Route",
    "RouteFollower",
    "ScenarioSpec",
    "ShipCommand",
    "ShipParams",
    "ShipSimulator",
    "ShipState",
    "Waypoint",
    "Weather",
    "actuate",
    "default_route",
    "derivatives",
    "rk4_step",
    "scenario_from_seed",
    "simulate",
    "wrap_angle",
]

FloatArray: TypeAlias = NDArray[np.float64]

DisturbanceKind = Literal["wind", "current", "waves"]

DISTURBANCE_LIMITS: dict[str, float] = {"wind": 60.0, "current": 5.0, "waves": 15.0}
"""The largest magnitude of each kind: wind and current in m/s, waves as Hs in metres."""


def wrap_angle(angle: float) -> float:
    """The same angle in (-pi, pi]."""
    wrapped = math.remainder(angle, 2.0 * math.pi)
    return math.pi if wrapped == -math.pi else wrapped


class _S(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Every float field must be finite; subclasses add their own checks after this one."""

    def __post_init__(self) -> None:
        for name in self.__struct_fields__:
            value = getattr(self, name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"{type(self).__name__}.{name} is {value}: give a finite number")


def _positive(owner: object, **values: float) -> None:
    for name, value in values.items():
        if not value > 0:
            raise ValueError(f"{type(owner).__name__}.{name} is {value}: it must be above 0")


# -- the ship and what it is told ---------------------------------------------------------


class ShipParams(_S, frozen=True, kw_only=True):
    """A 40 m coastal vessel of 400 t that cruises at about 5.8 m/s at 3 rps."""

    length: float = 40.0
    """Metres between perpendiculars; the lever arm of the weather's moments."""
    mass: float = 4.0e5
    inertia: float = 4.0e7
    """Yaw moment of inertia about the centre, kg m^2."""
    added_mass_surge: float = 2.0e4
    added_mass_sway: float = 3.2e5
    added_inertia: float = 2.0e7
    surge_linear: float = 2.0e3
    """N per m/s."""
    surge_quadratic: float = 4.0e3
    """N per (m/s)^2."""
    sway_linear: float = 2.4e4
    """N per m/s of sway, per m/s of speed."""
    sway_quadratic: float = 5.0e4
    """Cross-flow drag, N per (m/s)^2."""
    yaw_linear: float = 8.3e5
    """N m per rad/s of yaw rate, per m/s of speed."""
    yaw_quadratic: float = 5.0e7
    """N m per (rad/s)^2."""
    thrust: float = 2.0e4
    """N per rps^2."""
    thrust_speed_loss: float = 2.0e3
    """N per rps per m/s of advance."""
    rudder_force: float = 1.0e3
    """Rudder normal force, N per (m/s)^2 of inflow per unit sin(delta)."""
    rudder_slipstream: float = 1.2
    """(m/s)^2 of rudder inflow per rps^2 of the propeller."""
    rudder_lever: float = 20.0
    """Metres from the centre aft to the rudder."""
    rudder_drag: float = 0.2
    """Fraction of the normal force's sin(delta) component that is drag."""
    rudder_max: float = math.radians(35.0)
    rudder_rate: float = math.radians(5.0)
    """rad/s."""
    rps_max: float = 5.0
    rps_time_constant: float = 2.0
    air_density: float = 1.225
    frontal_area: float = 60.0
    lateral_area: float = 250.0
    wind_cx: float = 0.7
    wind_cy: float = 0.9
    wind_cn: float = 0.05
    wave_drift: float = 6.0e3
    """Mean drift force, N per m^2 of significant wave height squared."""
    wave_drift_surge: float = 0.3
    """Part of the drift force felt in surge (head and following seas)."""
    wave_drift_yaw: float = 0.05
    """Drift moment's lever as a fraction of the length."""
    wave_period: float = 8.0
    wave_oscillation: float = 0.5
    """First-order wave force amplitude as a fraction of the mean drift force."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _positive(
            self,
            length=self.length,
            mass=self.mass,
            inertia=self.inertia,
            rudder_max=self.rudder_max,
            rudder_rate=self.rudder_rate,
            rps_max=self.rps_max,
            rps_time_constant=self.rps_time_constant,
            wave_period=self.wave_period,
        )
        for name in self.__struct_fields__:
            value = getattr(self, name)
            if value < 0:
                raise ValueError(f"ShipParams.{name} is {value}: it must not be negative")
        if self.rudder_max >= math.pi / 2:
            raise ValueError("ShipParams.rudder_max must be below pi/2 rad (90 degrees)")


class ShipState(_S, frozen=True, kw_only=True):
    """What the ship's sensors report at time ``t``: pose, velocity over ground, actuators."""

    t: float
    """Seconds since the start of the run."""
    x: float
    """Metres north."""
    y: float
    """Metres east."""
    psi: float
    """Heading, rad in (-pi, pi], clockwise from north."""
    u: float
    """Surge velocity over ground, m/s."""
    v: float
    """Sway velocity over ground, m/s, positive to starboard."""
    r: float
    """Yaw rate, rad/s."""
    rudder: float = 0.0
    """The rudder's actual angle, rad; positive turns to starboard."""
    rps: float = 0.0
    """The propeller's actual revolutions per second."""

    def as_row(self) -> tuple[float, ...]:
        return (self.t, self.x, self.y, self.psi, self.u, self.v, self.r, self.rudder, self.rps)


COLUMNS = ("t", "x", "y", "psi", "u", "v", "r", "rudder", "rps")
"""The columns of a :class:`History`, in the order of :meth:`ShipState.as_row`."""


class ShipCommand(_S, frozen=True, kw_only=True):
    """What the bridge asks of the actuators; they saturate it and follow at their own pace."""

    rudder: float
    """rad; beyond ``rudder_max`` the rudder stops at its limit."""
    rps: float
    """Propeller revolutions per second, limited to [-rps_max / 2, rps_max]."""


# -- the weather ---------------------------------------------------------------------------


class Disturbance(_S, frozen=True, kw_only=True):
    """One kind of weather that sets in at ``onset_s`` and grows linearly over ``ramp_s``.

    ``direction`` is where the disturbance pushes *towards*, rad clockwise from north (so a
    wind from the west has direction pi/2). ``magnitude`` is the wind's speed or the
    current's speed in m/s, or the waves' significant height in metres.
    """

    kind: DisturbanceKind
    onset_s: float
    ramp_s: float
    magnitude: float
    direction: float

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.onset_s < 0:
            raise ValueError(f"Disturbance.onset_s is {self.onset_s}: it must not be negative")
        if self.ramp_s < 0:
            raise ValueError(f"Disturbance.ramp_s is {self.ramp_s}: it must not be negative")
        limit = DISTURBANCE_LIMITS[self.kind]
        if not 0 <= self.magnitude <= limit:
            raise ValueError(
                f"Disturbance.magnitude of {self.kind} is {self.magnitude}: "
                f"it must be within [0, {limit}]"
            )

    def level(self, t: float) -> float:
        """How much of the magnitude acts at time ``t``, from 0 to 1."""
        if t < self.onset_s:
            return 0.0
        if self.ramp_s == 0 or t >= self.onset_s + self.ramp_s:
            return 1.0
        return (t - self.onset_s) / self.ramp_s


class Weather(_S, frozen=True, kw_only=True):
    """The weather acting at time ``t``: every kind's present magnitude and direction."""

    t: float
    wind_speed: float = 0.0
    wind_direction: float = 0.0
    current_speed: float = 0.0
    current_direction: float = 0.0
    wave_height: float = 0.0
    wave_direction: float = 0.0


# -- the route -----------------------------------------------------------------------------


class Waypoint(_S, frozen=True):
    x: float
    y: float


class Route(_S, frozen=True, kw_only=True):
    """Waypoints sailed in order; a looped route goes back to the first after the last."""

    waypoints: list[Waypoint]
    loop: bool = True
    rps: float = 3.0
    """The propeller's revolutions on the route."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if len(self.waypoints) < 2:
            raise ValueError("Route.waypoints needs at least two waypoints")
        for a, b in zip(self.waypoints, self.waypoints[1:], strict=False):
            if math.hypot(b.x - a.x, b.y - a.y) < 1.0:
                raise ValueError(
                    f"Route.waypoints has two waypoints less than 1 m apart at ({b.x}, {b.y})"
                )


def default_route(seed: int = 0, *, radius: float = 600.0) -> Route:
    """An irregular hexagon around the origin, turned by an angle drawn from ``seed``.

    Its legs point in six directions, so a window of a few legs shows the ship (and a
    predictor learning from it) the weather from every side.
    """
    rng = np.random.default_rng(seed)
    turn = float(rng.uniform(0.0, 2.0 * math.pi))
    points = []
    for k in range(6):
        angle = turn + k * math.pi / 3.0 + float(rng.uniform(-0.15, 0.15))
        rho = radius * float(rng.uniform(0.8, 1.2))
        points.append(Waypoint(x=rho * math.cos(angle), y=rho * math.sin(angle)))
    return Route(waypoints=points)


# -- the scenario --------------------------------------------------------------------------


class ScenarioSpec(_S, frozen=True, kw_only=True):
    """Everything a run depends on: with the same spec, the same run, sample for sample."""

    seed: int = 0
    """Draws the waves' phase (and, through :func:`scenario_from_seed`, the rest)."""
    dt: float = 0.1
    """The integration step, seconds."""
    sample_period: float = 1.0
    """Seconds between the samples a run records; a whole number of steps."""
    duration_s: float = 1800.0
    params: ShipParams = msgspec.field(default_factory=ShipParams)
    route: Route = msgspec.field(default_factory=default_route)
    disturbances: list[Disturbance] = msgspec.field(default_factory=list)
    start: ShipState | None = None
    """The state at t = 0; by default at the first waypoint heading for the second, at
    cruising speed."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _positive(self, dt=self.dt, sample_period=self.sample_period, duration_s=self.duration_s)
        if self.dt > 1.0:
            raise ValueError(f"ScenarioSpec.dt is {self.dt}: at most 1 s keeps RK4 accurate")
        steps = round(self.sample_period / self.dt)
        if steps < 1 or abs(steps * self.dt - self.sample_period) > 1e-9 * self.sample_period:
            raise ValueError(
                f"ScenarioSpec.sample_period ({self.sample_period}) must be a whole number "
                f"of steps of dt ({self.dt})"
            )

    @property
    def steps_per_sample(self) -> int:
        return round(self.sample_period / self.dt)

    def initial_state(self) -> ShipState:
        if self.start is not None:
            return self.start
        a, b = self.route.waypoints[0], self.route.waypoints[1]
        psi = math.atan2(b.y - a.y, b.x - a.x)
        return ShipState(t=0.0, x=a.x, y=a.y, psi=psi, u=5.5, v=0.0, r=0.0, rps=self.route.rps)


def scenario_from_seed(
    seed: int,
    *,
    onset_s: float = 900.0,
    ramp_s: float = 60.0,
    duration_s: float = 1800.0,
    kinds: Sequence[DisturbanceKind] = ("wind", "current", "waves"),
) -> ScenarioSpec:
    """A weather front: each kind sets in at ``onset_s`` with a magnitude and a direction
    drawn from ``seed``; the route is :func:`default_route` of the same seed.

    The magnitudes are drawn from a strong breeze to a near gale (wind, 10-16 m/s), from
    1.2 to 2.3 knots (current) and from a moderate to a rough sea (waves, Hs 1.5-3 m).
    """
    rng = np.random.default_rng([seed, 1])
    ranges = {"wind": (10.0, 16.0), "current": (0.6, 1.2), "waves": (1.5, 3.0)}
    disturbances = [
        Disturbance(
            kind=kind,
            onset_s=onset_s,
            ramp_s=ramp_s,
            magnitude=float(rng.uniform(*ranges[kind])),
            direction=wrap_angle(float(rng.uniform(0.0, 2.0 * math.pi))),
        )
        for kind in kinds
    ]
    return ScenarioSpec(
        seed=seed, duration_s=duration_s, route=default_route(seed), disturbances=disturbances
    )


# -- the equations of motion ----------------------------------------------------------------

Vector6 = tuple[float, float, float, float, float, float]
"""x, y, psi, u_r, v_r, r: the integrated state, velocities through the water."""
Forces = tuple[float, float, float]
"""X, Y, N in the body frame."""
_CALM: Forces = (0.0, 0.0, 0.0)


def derivatives(
    p: ShipParams,
    s: Vector6,
    rudder: float,
    rps: float,
    external: Forces = _CALM,
    current: tuple[float, float] = (0.0, 0.0),
) -> Vector6:
    """The time derivative of ``s`` under the actuators' present values, an external force
    in the body frame and a current (north, east, m/s)."""
    _, _, psi, u, v, r = s
    speed = math.hypot(u, v)
    m_u = p.mass + p.added_mass_surge
    m_v = p.mass + p.added_mass_sway
    i_z = p.inertia + p.added_inertia

    x_hull = -p.surge_linear * u - p.surge_quadratic * abs(u) * u
    y_hull = -p.sway_linear * speed * v - p.sway_quadratic * abs(v) * v
    n_hull = -p.yaw_linear * speed * r - p.yaw_quadratic * abs(r) * r

    x_prop = p.thrust * rps * abs(rps) - p.thrust_speed_loss * rps * u

    inflow = u * u + (p.rudder_slipstream * rps * rps if rps > 0 else 0.0)
    normal = p.rudder_force * inflow * math.sin(rudder)
    x_rud = -p.rudder_drag * normal * math.sin(rudder)
    y_rud = -normal * math.cos(rudder)
    n_rud = p.rudder_lever * normal * math.cos(rudder)

    ext_x, ext_y, ext_n = external
    du = (m_v * v * r + x_hull + x_prop + x_rud + ext_x) / m_u
    dv = (-m_u * u * r + y_hull + y_rud + ext_y) / m_v
    dr = (n_hull + n_rud + ext_n) / i_z

    c, s_ = math.cos(psi), math.sin(psi)
    dx = u * c - v * s_ + current[0]
    dy = u * s_ + v * c + current[1]
    return (dx, dy, r, du, dv, dr)


def rk4_step(
    p: ShipParams,
    s: Vector6,
    dt: float,
    rudder: float,
    rps: float,
    external: Forces = _CALM,
    current: tuple[float, float] = (0.0, 0.0),
) -> Vector6:
    """One fourth-order Runge-Kutta step with the actuators and the weather held."""

    def f(state: Vector6) -> Vector6:
        return derivatives(p, state, rudder, rps, external, current)

    def ax(a: Vector6, k: Vector6, h: float) -> Vector6:
        return (
            a[0] + h * k[0],
            a[1] + h * k[1],
            a[2] + h * k[2],
            a[3] + h * k[3],
            a[4] + h * k[4],
            a[5] + h * k[5],
        )

    k1 = f(s)
    k2 = f(ax(s, k1, dt / 2))
    k3 = f(ax(s, k2, dt / 2))
    k4 = f(ax(s, k3, dt))
    w = dt / 6.0
    return (
        s[0] + w * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]),
        s[1] + w * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]),
        s[2] + w * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2]),
        s[3] + w * (k1[3] + 2 * k2[3] + 2 * k3[3] + k4[3]),
        s[4] + w * (k1[4] + 2 * k2[4] + 2 * k3[4] + k4[4]),
        s[5] + w * (k1[5] + 2 * k2[5] + 2 * k3[5] + k4[5]),
    )


def actuate(
    p: ShipParams, rudder: float, rps: float, command: ShipCommand, dt: float
) -> tuple[float, float]:
    """The rudder and propeller after ``dt`` of following ``command`` (saturated)."""
    target = min(max(command.rudder, -p.rudder_max), p.rudder_max)
    step = p.rudder_rate * dt
    rudder = rudder + min(max(target - rudder, -step), step)
    wanted = min(max(command.rps, -p.rps_max / 2), p.rps_max)
    rps = rps + (wanted - rps) * (1.0 - math.exp(-dt / p.rps_time_constant))
    return rudder, rps


# -- the simulator -------------------------------------------------------------------------


class ShipSimulator:
    """The ship in its weather, stepped at ``spec.dt``; deterministic for a given spec."""

    def __init__(self, spec: ScenarioSpec) -> None:
        self.spec = spec
        self.params = spec.params
        start = spec.initial_state()
        self._t = start.t
        self._rudder = start.rudder
        self._rps = start.rps
        # the start state's velocity is over ground; the water moves with the current
        cn, ce = self._current(start.t)
        c, s = math.cos(start.psi), math.sin(start.psi)
        self._s: Vector6 = (
            start.x,
            start.y,
            start.psi,
            start.u - (c * cn + s * ce),
            start.v - (-s * cn + c * ce),
            start.r,
        )
        rng = np.random.default_rng([spec.seed, 2])
        self._wave_phase = float(rng.uniform(0.0, 2.0 * math.pi))
        self._steps = 0

    @property
    def t(self) -> float:
        return self._t

    def _by_kind(self, kind: str, t: float) -> tuple[float, float]:
        """The summed vector (north, east) of every disturbance of ``kind`` at ``t``."""
        n = e = 0.0
        for d in self.spec.disturbances:
            if d.kind == kind:
                m = d.magnitude * d.level(t)
                n += m * math.cos(d.direction)
                e += m * math.sin(d.direction)
        return n, e

    def _current(self, t: float) -> tuple[float, float]:
        return self._by_kind("current", t)

    def weather(self) -> Weather:
        """The weather acting now."""
        wn, we = self._by_kind("wind", self._t)
        cn, ce = self._by_kind("current", self._t)
        hn, he = self._by_kind("waves", self._t)

        def polar(n: float, e: float) -> tuple[float, float]:
            return math.hypot(n, e), (math.atan2(e, n) if n or e else 0.0)

        ws, wd = polar(wn, we)
        cs, cd = polar(cn, ce)
        hs, hd = polar(hn, he)
        return Weather(
            t=self._t,
            wind_speed=ws,
            wind_direction=wd,
            current_speed=cs,
            current_direction=cd,
            wave_height=hs,
            wave_direction=hd,
        )

    def weather_forces(self) -> Forces:
        """The wind's and the waves' force and moment on the ship now, in the body frame."""
        p = self.params
        _, _, psi, u_r, v_r, _ = self._s
        c, s = math.cos(psi), math.sin(psi)
        cn, ce = self._current(self._t)
        u = u_r + c * cn + s * ce
        v = v_r - s * cn + c * ce
        fx = fy = fn = 0.0

        wn, we = self._by_kind("wind", self._t)
        if wn or we:
            # the air's velocity relative to the ship, in the body frame
            ax = c * wn + s * we - u
            ay = -s * wn + c * we - v
            q = 0.5 * p.air_density * (ax * ax + ay * ay)
            gamma = math.atan2(ay, ax)
            fx += q * p.frontal_area * p.wind_cx * math.cos(gamma)
            fy += q * p.lateral_area * p.wind_cy * math.sin(gamma)
            fn += q * p.lateral_area * p.length * p.wind_cn * math.sin(2.0 * gamma)

        hn, he = self._by_kind("waves", self._t)
        height = math.hypot(hn, he)
        if height > 0:
            beta = math.atan2(he, hn) - psi  # where the waves go, seen from the ship
            omega = 2.0 * math.pi / p.wave_period
            swell = 1.0 + p.wave_oscillation * math.sin(omega * self._t + self._wave_phase)
            force = p.wave_drift * height * height * swell
            fx += p.wave_drift_surge * force * math.cos(beta)
            fy += force * math.sin(beta)
            fn += p.wave_drift_yaw * p.length * force * math.sin(2.0 * beta)
        return (fx, fy, fn)

    def state(self) -> ShipState:
        x, y, psi, u_r, v_r, r = self._s
        cn, ce = self._current(self._t)
        c, s = math.cos(psi), math.sin(psi)
        return ShipState(
            t=self._t,
            x=x,
            y=y,
            psi=wrap_angle(psi),
            u=u_r + c * cn + s * ce,
            v=v_r - s * cn + c * ce,
            r=r,
            rudder=self._rudder,
            rps=self._rps,
        )

    def step(self, command: ShipCommand) -> None:
        """Advance one step of ``spec.dt`` under ``command``."""
        p, dt = self.params, self.spec.dt
        external = self.weather_forces()
        # the water's own acceleration (a ramping current) carries the ship with it: the
        # integrated velocities are through the water, so a ramp needs no extra term
        current = self._current(self._t + dt / 2)
        self._rudder, self._rps = actuate(p, self._rudder, self._rps, command, dt)
        self._s = rk4_step(p, self._s, dt, self._rudder, self._rps, external, current)
        psi = self._s[2]
        if abs(psi) > math.pi:
            self._s = (self._s[0], self._s[1], wrap_angle(psi), *self._s[3:])
        self._steps += 1
        self._t = self._steps * dt
        if not all(math.isfinite(value) for value in self._s):
            raise FloatingPointError(f"the ship's state became non-finite at t={self._t}")


# -- sailing a route -----------------------------------------------------------------------


class RouteFollower:
    """Line-of-sight guidance along the route's legs and a PID heading autopilot.

    The desired course points at a spot ``lookahead`` metres ahead on the present leg; the
    desired heading is that course less the crab angle (low-pass filtered on steady
    courses), so a steady current or wind does not leave the ship beside its route. The
    next leg is taken at the wheel-over point, early enough for a turn of ``turn_radius``
    plus ``acceptance`` metres for the rudder and the hull to respond. The autopilot's gains
    suit the default ship (at cruising speed a Nomoto gain near 0.2 1/s and a time constant
    near 12 s).
    """

    def __init__(
        self,
        route: Route,
        *,
        lookahead: float = 150.0,
        acceptance: float = 80.0,
        turn_radius: float = 150.0,
        kp: float = 1.0,
        kd: float = 10.0,
        ki: float = 0.005,
        crab_time_constant: float = 20.0,
        steady_rate: float = 0.005,
        integral_band: float = math.radians(10.0),
    ) -> None:
        self.route = route
        self.lookahead = lookahead
        self.acceptance = acceptance
        self.turn_radius = turn_radius
        self.kp, self.kd, self.ki = kp, kd, ki
        self.crab_time_constant = crab_time_constant
        self.steady_rate = steady_rate
        self.integral_band = integral_band
        self.leg = 0
        self._integral = 0.0
        self._crab = 0.0
        self.finished = False

    def _leg_points(self) -> tuple[Waypoint, Waypoint]:
        points = self.route.waypoints
        a = points[self.leg % len(points)]
        b = points[(self.leg + 1) % len(points)]
        return a, b

    def _wheel_over(self, a: Waypoint, b: Waypoint) -> float:
        """How far before ``b`` to start turning onto the next leg: where a turn of
        ``turn_radius`` meets both legs, plus ``acceptance``."""
        points = self.route.waypoints
        if not self.route.loop and self.leg + 2 >= len(points):
            return self.acceptance
        c = points[(self.leg + 2) % len(points)]
        change = wrap_angle(math.atan2(c.y - b.y, c.x - b.x) - math.atan2(b.y - a.y, b.x - a.x))
        return self.acceptance + self.turn_radius * math.tan(min(abs(change), 2.5) / 2.0)

    def command(self, state: ShipState, dt: float) -> ShipCommand:
        """The rudder and revolutions for the next ``dt`` seconds."""
        points = self.route.waypoints
        a, b = self._leg_points()
        leg_angle = math.atan2(b.y - a.y, b.x - a.x)
        length = math.hypot(b.x - a.x, b.y - a.y)
        along = (state.x - a.x) * math.cos(leg_angle) + (state.y - a.y) * math.sin(leg_angle)
        if along > length - self._wheel_over(a, b) and not self.finished:
            if self.route.loop or self.leg + 2 < len(points):
                self.leg += 1
                a, b = self._leg_points()
                leg_angle = math.atan2(b.y - a.y, b.x - a.x)
            else:
                self.finished = True
        cross = -(state.x - a.x) * math.sin(leg_angle) + (state.y - a.y) * math.cos(leg_angle)
        course = leg_angle - math.atan2(cross, self.lookahead)

        # the crab angle is learnt on steady courses only: in a turn the drift angle is the
        # turn's own, not the weather's
        if state.u > 0.5 and abs(state.r) < self.steady_rate:
            crab = math.atan2(state.v, state.u)
            self._crab += (crab - self._crab) * (1.0 - math.exp(-dt / self.crab_time_constant))
        error = wrap_angle(course - self._crab - state.psi)

        limit = math.radians(35.0)
        # integrate near the course only, so a turn does not wind the integrator up
        if abs(error) < self.integral_band:
            bound = limit / self.ki if self.ki > 0 else 0.0
            self._integral = min(max(self._integral + error * dt, -bound), bound)
        rudder = self.kp * error - self.kd * state.r + self.ki * self._integral
        rps = 0.0 if self.finished else self.route.rps
        return ShipCommand(rudder=min(max(rudder, -limit), limit), rps=rps)


# -- a run ---------------------------------------------------------------------------------


class History:
    """The ship's sampled states, one row per sample (columns :data:`COLUMNS`), oldest first.

    The array is read-only; the heading column holds wrapped angles.
    """

    __slots__ = ("_data",)

    def __init__(self, data: FloatArray | Sequence[Sequence[float]]) -> None:
        array = np.array(data, dtype=np.float64)
        if array.ndim != 2 or array.shape[1] != len(COLUMNS):
            raise ValueError(
                f"a history needs rows of {len(COLUMNS)} values {COLUMNS}, got shape {array.shape}"
            )
        if not np.isfinite(array).all():
            row = int(np.argwhere(~np.isfinite(array))[0][0])
            raise ValueError(f"a history holds a non-finite value in row {row}")
        if len(array) > 1 and not (np.diff(array[:, 0]) > 0).all():
            raise ValueError("a history's times must increase from row to row")
        array.flags.writeable = False
        self._data = array

    @classmethod
    def from_states(cls, states: Sequence[ShipState]) -> History:
        if not states:
            return cls(np.empty((0, len(COLUMNS))))
        return cls([s.as_row() for s in states])

    @property
    def data(self) -> FloatArray:
        return self._data

    def column(self, name: str) -> FloatArray:
        return self._data[:, COLUMNS.index(name)]

    @property
    def t(self) -> FloatArray:
        return self._data[:, 0]

    def __len__(self) -> int:
        return len(self._data)

    def __iter__(self) -> Iterator[ShipState]:
        for row in self._data:
            yield ShipState(**dict(zip(COLUMNS, (float(v) for v in row), strict=True)))

    def states(self) -> list[ShipState]:
        return list(self)

    def between(self, start: float, end: float = math.inf) -> History:
        """The samples with ``start <= t < end``."""
        t = self.t
        return History(self._data[(t >= start) & (t < end)])

    def __getitem__(self, index: slice) -> History:
        return History(self._data[index])

    def concat(self, other: History) -> History:
        return History(np.concatenate([self._data, other._data]))


def simulate(
    spec: ScenarioSpec,
    *,
    follower: RouteFollower | None = None,
    controller: Callable[[ShipState, float], ShipCommand] | None = None,
    on_sample: Callable[[ShipState, Weather], Any] | None = None,
) -> History:
    """Run ``spec`` to its end and return the states sampled every ``spec.sample_period``.

    The ship follows its route (a fresh :class:`RouteFollower` unless one is given), or obeys
    ``controller`` when that is given. The controller is asked at every step.
    """
    sim = ShipSimulator(spec)
    if controller is None:
        chosen = follower if follower is not None else RouteFollower(spec.route)
        controller = chosen.command
    every = spec.steps_per_sample
    total = round(spec.duration_s / spec.dt)
    rows: list[tuple[float, ...]] = []
    state = sim.state()
    for k in range(total + 1):
        if k % every == 0:
            rows.append(state.as_row())
            if on_sample is not None:
                on_sample(state, sim.weather())
        if k == total:
            break
        sim.step(controller(state, spec.dt))
        state = sim.state()
    return History(rows)
