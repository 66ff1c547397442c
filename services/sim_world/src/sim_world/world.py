"""World files: YAML validated by msgspec Structs, errors with file:line:col.

    seed: 7
    room: {width: 10.0, height: 8.0}
    obstacles:
      - {kind: circle, x: 3.0, y: 2.0, r: 0.4}
      - {kind: box, x: 6.0, y: 5.0, w: 1.0, h: 0.6, theta: 0.3}
    robots:
      - name: tb1
        start: {x: 1.0, y: 1.0, theta: 0.0}
        route: [{x: 8.0, y: 1.0}, {x: 8.0, y: 6.0}]
    occlusions:
      - {robot: tb1, mode: sector, start_angle: 1.2, width: 0.8, t_start: 10, t_end: 40}

Angles are radians, counter-clockwise; occlusion angles are in the robot's frame
(0 = straight ahead), as are the lidar's beams.

Beyond the types, a world must be possible (:func:`check_world`): every number finite
(``.nan`` and ``.inf`` are refused; leave ``t_end`` out for an occlusion that lasts to
the end of the run), the lidar's ``range_min`` below its ``range_max`` and its
``rate_hz`` at most ``physics_hz``, obstacles centred in the room, robots starting
inside the room clear of obstacles and of each other, route points in the room where
the robot can reach them, occlusions naming a robot and ending after they start.

Shipped worlds (``sim_world/worlds/*.yaml``) are named by their stem:
:func:`shipped_worlds`, :func:`find_world`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
from rap_schemas.limits import MAX_YAML_BYTES
from rap_schemas.yamlconf import (
    YamlError,
    parse_yaml,
    read_text_file,
    render_location,
)

__all__ = [
    "MAX_ROOM",
    "MAX_SPEED",
    "REACHED",
    "Arc",
    "Box",
    "Circle",
    "Lidar",
    "Occlusion",
    "Point",
    "Pose",
    "RobotSpec",
    "Room",
    "WorldError",
    "WorldSpec",
    "check_world",
    "default_world_path",
    "find_world",
    "load_world",
    "parse_world",
    "shipped_worlds",
]

MAX_ROOM = 10_000.0
"""Metres: the longest side a room may have."""
MAX_SPEED = 1_000.0
"""The fastest a robot may be (m/s, rad/s): the bound of a ``Twist`` on the wire."""
REACHED = 0.25
"""Metres from a waypoint at which the robot's centre counts as having reached it."""

Positive = Annotated[float, msgspec.Meta(gt=0)]
NonNegative = Annotated[float, msgspec.Meta(ge=0)]
Speed = Annotated[float, msgspec.Meta(gt=0, le=MAX_SPEED)]
Side = Annotated[float, msgspec.Meta(gt=0, le=MAX_ROOM)]

WORLDS = Path(__file__).with_name("worlds")


class _S(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    pass


class Point(_S, frozen=True):
    x: float
    y: float


class Pose(_S, frozen=True, kw_only=True):
    x: float
    y: float
    theta: float = 0.0


class Room(_S, frozen=True):
    width: Side = 10.0
    height: Side = 8.0


class Circle(_S, frozen=True, tag="circle", tag_field="kind"):
    x: float
    y: float
    r: Positive


class Box(_S, frozen=True, kw_only=True, tag="box", tag_field="kind"):
    x: float
    y: float
    w: Positive
    h: Positive
    theta: float = 0.0

    def corners(self) -> list[tuple[float, float]]:
        c, s = math.cos(self.theta), math.sin(self.theta)
        hw, hh = self.w / 2, self.h / 2
        return [
            (self.x + c * dx - s * dy, self.y + s * dx + c * dy)
            for dx, dy in ((-hw, -hh), (hw, -hh), (hw, hh), (-hw, hh))
        ]


class Lidar(_S, frozen=True, kw_only=True):
    beams: Annotated[int, msgspec.Meta(ge=1, le=10_000)] = 360
    angle_min: Annotated[float, msgspec.Meta(ge=-2 * math.pi, le=2 * math.pi)] = -math.pi
    range_min: NonNegative = 0.1
    range_max: Annotated[float, msgspec.Meta(gt=0, le=1e6)] = 12.0
    rate_hz: Annotated[float, msgspec.Meta(ge=0.001, le=1000.0)] = 5.0
    """Scans per second of sim time, at most ``physics_hz``."""
    noise_std: NonNegative = 0.0

    @property
    def angle_increment(self) -> float:
        return 2 * math.pi / self.beams


class RobotSpec(_S, frozen=True, kw_only=True):
    name: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_\-]+$")]
    start: Pose
    route: list[Point] = []
    radius: Positive = 0.17
    wheel_separation: Positive = 0.233
    max_linear: Speed = 0.31
    max_angular: Speed = 1.9
    loop_route: bool = False
    obstacle_memory: NonNegative = 10.0
    """Seconds the navigator remembers obstacles it saw within 2.5 m (a decaying local
    costmap, as real navigation stacks keep): what a spin shows stays known for a while.
    0: react to the current scan only."""


class Arc(_S, frozen=True):
    start_angle: float
    width: Annotated[float, msgspec.Meta(gt=0, le=2 * math.pi)]


class Occlusion(_S, frozen=True, kw_only=True):
    """Something on the robot blocks part of its lidar from ``t_start`` to ``t_end``
    (None: to the end of the run).

    ``sector``: one arc (``start_angle``, ``width``); ``arcs``: several (``arcs``);
    ``global``: all but a 60 degree window centred on ``start_angle``; ``random``: 1 to
    3 arcs of 15 to 90 degrees drawn anew every ``period`` s (seeded)."""

    robot: str
    mode: Literal["sector", "arcs", "global", "random"]
    t_start: NonNegative = 0.0
    t_end: float | None = None
    start_angle: float = 0.0
    width: Annotated[float, msgspec.Meta(ge=0, le=2 * math.pi)] = 0.0
    arcs: list[Arc] = []
    period: Positive = 5.0


class WorldSpec(_S, frozen=True, kw_only=True):
    seed: Annotated[int, msgspec.Meta(ge=0)] = 0
    room: Room = Room()
    obstacles: list[Circle | Box] = []
    robots: Annotated[list[RobotSpec], msgspec.Meta(min_length=1)]
    lidar: Lidar = Lidar()
    occlusions: list[Occlusion] = []
    physics_hz: Annotated[float, msgspec.Meta(gt=0, le=10_000.0)] = 50.0


class WorldError(YamlError):
    """A world that cannot be used; the message starts with ``file:line:col`` (or, for a
    world built in code, ``source: at `$.path```) and ends with how to fix it."""


Location = tuple[Any, ...]


def parse_world(text: str, source: str = "<world>") -> WorldSpec:
    """Validate a world; errors read ``source:line:col: what - how to fix``."""
    doc = parse_yaml(text, source, what="world file", error=WorldError)
    for loc, _ in _non_finite(doc.data):
        written = getattr(doc.node_at(loc), "value", "")
        raise doc.error(loc, _non_finite_problem(loc, str(written)))
    world = doc.convert(WorldSpec, strict=False)
    for loc, problem in _problems(world):
        raise doc.error(loc, problem)
    return world


def check_world(world: WorldSpec, source: str = "<world>") -> WorldSpec:
    """``world`` if it is possible (see the module docstring), else :class:`WorldError`
    naming the field as ``$.path``. For worlds built in code; files get the same checks
    from :func:`parse_world`, with their line and column."""
    for loc, problem in _problems(world):
        raise WorldError(f"{source}: at `{render_location(loc)}`: {problem}", source=source)
    return world


def load_world(path: str | Path) -> WorldSpec:
    """The world in the file ``path`` (a missing, binary or oversized file is a
    :class:`WorldError` naming it, as is an impossible world)."""
    text = read_text_file(path, what="world file", error=WorldError, max_bytes=MAX_YAML_BYTES)
    return parse_world(text, str(path))


def shipped_worlds() -> list[str]:
    """The names of the worlds that ship with the package."""
    return sorted(p.stem for p in WORLDS.glob("*.yaml"))


def find_world(ref: str | Path) -> Path:
    """The world file ``ref`` names: a bare name (no ``/``, no suffix) is a shipped world
    (``corridor``), anything else a path (``./corridor`` for a file of that name)."""
    text = str(ref)
    names = shipped_worlds()
    listing = ", ".join(names)
    bare = isinstance(ref, str) and "/" not in text and "\\" not in text and "." not in text
    if bare:
        if text in names:
            return WORLDS / f"{text}.yaml"
        raise WorldError(
            f"{text!r} is not a shipped world; the shipped worlds are {listing} - give one "
            "of them, or the path of a world file (./name for a file in this directory)",
            source=text,
        )
    path = Path(text)
    if not path.exists():
        raise WorldError(
            f"{path}: no such world file; the shipped worlds are {listing} - give one of "
            "them by name, or the path of an existing world file",
            source=text,
        )
    return path


def default_world_path(name: str = "default") -> Path:
    """A world that ships with the package, by name (see :func:`shipped_worlds`)."""
    names = shipped_worlds()
    if name not in names:
        raise WorldError(
            f"{name!r} is not a shipped world; the shipped worlds are {', '.join(names)} - "
            "give one of them",
            source=name,
        )
    return WORLDS / f"{name}.yaml"


# -- the checks ----------------------------------------------------------------------------


def _non_finite(data: Any) -> Iterator[tuple[Location, float]]:
    """Every NaN or infinite float in plain data, in document order, with its location."""
    stack: list[tuple[Location, Any]] = [((), data)]
    while stack:
        loc, value = stack.pop()
        if isinstance(value, float) and not math.isfinite(value):
            yield loc, value
        elif isinstance(value, dict):
            stack.extend(((*loc, k), v) for k, v in reversed(value.items()))
        elif isinstance(value, list):
            stack.extend(((*loc, i), v) for i, v in reversed(list(enumerate(value))))


def _non_finite_problem(loc: Location, written: str) -> str:
    shown = written or "the value"
    fix = "write a finite number"
    if loc and loc[-1] == "t_end":
        fix = "write a finite time, or leave t_end out for an occlusion that lasts to the end"
    return f"{shown} at `{render_location(loc)}` is not a finite number - {fix}"


def _clearance(x: float, y: float, ob: Circle | Box) -> float:
    """Distance from (x, y) to the obstacle's surface; negative inside it."""
    dx, dy = x - ob.x, y - ob.y
    if isinstance(ob, Circle):
        return math.hypot(dx, dy) - ob.r
    c, s = math.cos(ob.theta), math.sin(ob.theta)
    u = abs(c * dx + s * dy) - ob.w / 2
    v = abs(-s * dx + c * dy) - ob.h / 2
    if u > 0 or v > 0:
        return math.hypot(max(u, 0.0), max(v, 0.0))
    return max(u, v)


def _describe(i: int, ob: Circle | Box) -> str:
    return f"obstacle {i} ({'circle' if isinstance(ob, Circle) else 'box'} at ({ob.x:g}, {ob.y:g}))"


def _problems(world: WorldSpec) -> Iterator[tuple[Location, str]]:
    """Each way ``world`` is impossible: (location, what - how to fix)."""
    for loc, value in _non_finite(msgspec.to_builtins(world)):
        yield loc, _non_finite_problem(loc, repr(value))
        return  # the other checks assume finite numbers
    yield from _lidar_problems(world)
    yield from _obstacle_problems(world)
    yield from _robot_problems(world)
    yield from _occlusion_problems(world)


def _lidar_problems(world: WorldSpec) -> Iterator[tuple[Location, str]]:
    lidar = world.lidar
    if lidar.range_min >= lidar.range_max:
        yield (
            ("lidar", "range_min"),
            f"lidar range_min {lidar.range_min:g} is not below range_max {lidar.range_max:g}, "
            "so no return could be kept - make range_min smaller than range_max",
        )
    if lidar.rate_hz > world.physics_hz:
        yield (
            ("lidar", "rate_hz"),
            f"lidar rate_hz {lidar.rate_hz:g} is above physics_hz {world.physics_hz:g}, but "
            "a scan is taken at most once per physics step - lower rate_hz or raise physics_hz",
        )


def _obstacle_problems(world: WorldSpec) -> Iterator[tuple[Location, str]]:
    w, h = world.room.width, world.room.height
    for i, ob in enumerate(world.obstacles):
        if not (0 <= ob.x <= w and 0 <= ob.y <= h):
            yield (
                ("obstacles", i),
                f"{_describe(i, ob)} is outside the {w:g} x {h:g} m room - move its centre "
                f"inside (0 <= x <= {w:g}, 0 <= y <= {h:g})",
            )


def _robot_problems(world: WorldSpec) -> Iterator[tuple[Location, str]]:
    w, h = world.room.width, world.room.height
    robots: Sequence[RobotSpec] = world.robots
    names = [r.name for r in robots]
    for i, robot in enumerate(robots):
        if robot.name in names[:i]:  # point at the second use
            yield (
                ("robots", i, "name"),
                f"robot name {robot.name!r} is used twice - give each robot its own name",
            )
    for i, robot in enumerate(robots):
        r, start = robot.radius, robot.start
        if 2 * r > min(w, h):
            yield (
                ("robots", i, "radius"),
                f"robot {robot.name!r} (radius {r:g} m) does not fit in the {w:g} x {h:g} m "
                "room - make the radius smaller or the room larger",
            )
            continue
        if not (r <= start.x <= w - r and r <= start.y <= h - r):
            yield (
                ("robots", i, "start"),
                f"robot {robot.name!r} starts at ({start.x:g}, {start.y:g}), not inside the "
                f"{w:g} x {h:g} m room (with its radius of {r:g} m it needs {r:g} <= x <= "
                f"{w - r:g} and {r:g} <= y <= {h - r:g}) - move the start inside the room",
            )
        for j, ob in enumerate(world.obstacles):
            if _clearance(start.x, start.y, ob) < r:
                yield (
                    ("robots", i, "start"),
                    f"robot {robot.name!r} starts at ({start.x:g}, {start.y:g}), overlapping "
                    f"{_describe(j, ob)} - move the start or the obstacle",
                )
        for other in robots[:i]:
            gap = math.hypot(start.x - other.start.x, start.y - other.start.y)
            if gap < r + other.radius:
                yield (
                    ("robots", i, "start"),
                    f"robot {robot.name!r} starts at ({start.x:g}, {start.y:g}), overlapping "
                    f"robot {other.name!r} - start the robots at least {r + other.radius:g} m "
                    "apart",
                )
        yield from _route_problems(world, i, robot)


def _route_problems(world: WorldSpec, i: int, robot: RobotSpec) -> Iterator[tuple[Location, str]]:
    w, h, r = world.room.width, world.room.height, robot.radius
    for k, p in enumerate(robot.route):
        at = ("robots", i, "route", k)
        what = f"route point {k} of robot {robot.name!r}, ({p.x:g}, {p.y:g}),"
        if not (0 <= p.x <= w and 0 <= p.y <= h):
            yield (
                at,
                f"{what} is outside the {w:g} x {h:g} m room - move it inside "
                f"(0 <= x <= {w:g}, 0 <= y <= {h:g})",
            )
            continue
        # the nearest the robot's centre can come: kept r from the walls and obstacles
        cx, cy = min(max(p.x, r), w - r), min(max(p.y, r), h - r)
        if math.hypot(p.x - cx, p.y - cy) >= REACHED:
            yield (
                at,
                f"{what} is too close to a wall: the robot's centre (radius {r:g} m) cannot "
                f"come within {REACHED:g} m of it, the distance that counts as reached - "
                "move it away from the wall",
            )
        for j, ob in enumerate(world.obstacles):
            nearest = r - _clearance(p.x, p.y, ob)
            if nearest >= REACHED:
                yield (
                    at,
                    f"{what} lies inside {_describe(j, ob)}: the robot (radius {r:g} m) "
                    f"comes no nearer than {nearest:.2f} m, and a point counts as reached "
                    f"within {REACHED:g} m - move it clear of the obstacle",
                )


def _occlusion_problems(world: WorldSpec) -> Iterator[tuple[Location, str]]:
    names = [r.name for r in world.robots]
    for i, occ in enumerate(world.occlusions):
        if occ.robot not in names:
            yield (
                ("occlusions", i, "robot"),
                f"occlusion names robot {occ.robot!r}, but the robots are {names} - name one "
                "of them",
            )
        if occ.t_end is not None and occ.t_end <= occ.t_start:
            yield (
                ("occlusions", i),
                f"occlusion ends (t_end={occ.t_end}) before it starts (t_start={occ.t_start}) "
                "- make t_end later than t_start, or leave it out to last to the end",
            )
        if occ.mode == "sector" and occ.width <= 0:
            yield (("occlusions", i), "a sector occlusion needs a width > 0 (radians) - add one")
        if occ.mode == "arcs" and not occ.arcs:
            yield (
                ("occlusions", i),
                "an arcs occlusion needs at least one arc - add arcs: [{start_angle, width}]",
            )
