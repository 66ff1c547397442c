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
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import msgspec
from rap_schemas.yamlconf import YamlDocument, YamlError, parse_yaml

__all__ = [
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
    "load_world",
    "parse_world",
]

Positive = Annotated[float, msgspec.Meta(gt=0)]
NonNegative = Annotated[float, msgspec.Meta(ge=0)]


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
    width: Positive = 10.0
    height: Positive = 8.0


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
    angle_min: float = -math.pi
    range_min: NonNegative = 0.1
    range_max: Positive = 12.0
    rate_hz: Positive = 5.0
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
    max_linear: Positive = 0.31
    max_angular: Positive = 1.9
    loop_route: bool = False
    obstacle_memory: NonNegative = 10.0
    """Seconds the navigator remembers obstacles it saw within 2.5 m (a decaying local
    costmap, as real navigation stacks keep): what a spin shows stays known for a while.
    0: react to the current scan only."""


class Arc(_S, frozen=True):
    start_angle: float
    width: Annotated[float, msgspec.Meta(gt=0, le=2 * math.pi)]


class Occlusion(_S, frozen=True, kw_only=True):
    """Something on the robot blocks part of its lidar from ``t_start`` to ``t_end``.

    ``sector``: one arc (``start_angle``, ``width``); ``arcs``: several (``arcs``);
    ``global``: all but a 60 degree window centred on ``start_angle``; ``random``: 1 to
    3 arcs of 15 to 90 degrees drawn anew every ``period`` s (seeded)."""

    robot: str
    mode: Literal["sector", "arcs", "global", "random"]
    t_start: NonNegative = 0.0
    t_end: float = math.inf
    start_angle: float = 0.0
    width: Annotated[float, msgspec.Meta(ge=0, le=2 * math.pi)] = 0.0
    arcs: list[Arc] = []
    period: Positive = 5.0


class WorldSpec(_S, frozen=True, kw_only=True):
    seed: int = 0
    room: Room = Room()
    obstacles: list[Circle | Box] = []
    robots: Annotated[list[RobotSpec], msgspec.Meta(min_length=1)]
    lidar: Lidar = Lidar()
    occlusions: list[Occlusion] = []
    physics_hz: Positive = 50.0


class WorldError(YamlError):
    """A world file that cannot be used; the message starts with ``file:line:col``."""


def parse_world(text: str, source: str = "<world>") -> WorldSpec:
    """Validate a world; errors read ``source:line:col: what - at `$.path``."""
    doc = parse_yaml(text, source, what="world file", error=WorldError)
    world = doc.convert(WorldSpec, strict=False)
    _check_references(world, doc)
    return world


def _check_references(world: WorldSpec, doc: YamlDocument) -> None:
    names = [r.name for r in world.robots]
    for i, robot in enumerate(world.robots):
        if robot.name in names[:i]:  # point at the second use
            raise doc.error(
                ("robots", i, "name"),
                f"robot name {robot.name!r} is used twice; names must be unique",
            )
    for i, occ in enumerate(world.occlusions):
        if occ.robot not in names:
            raise doc.error(
                ("occlusions", i, "robot"),
                f"occlusion names robot {occ.robot!r}, but the robots are {names}",
            )
        if occ.t_end <= occ.t_start:
            raise doc.error(
                ("occlusions", i),
                f"occlusion ends (t_end={occ.t_end}) before it starts (t_start={occ.t_start})",
            )
        if occ.mode == "sector" and occ.width <= 0:
            raise doc.error(("occlusions", i), "a sector occlusion needs a width > 0 (radians)")
        if occ.mode == "arcs" and not occ.arcs:
            raise doc.error(("occlusions", i), "an arcs occlusion needs at least one arc")


def load_world(path: str | Path) -> WorldSpec:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise WorldError(f"{p}: cannot read the world file: {exc}") from None
    return parse_world(text, str(p))


def default_world_path(name: str = "default") -> Path:
    """A world that ships with the package: default, corridor, obstacles_only."""
    path = Path(__file__).with_name("worlds") / f"{name}.yaml"
    if not path.exists():
        names = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise WorldError(f"no shipped world {name!r}; the shipped worlds are {names}")
    return path
