"""The simulation: robots as pymunk bodies among the world's walls and obstacles.

Each physics step (``physics_hz``) every robot's command is decided (a velocity
override, else the spin-plan executor, else nominal navigation), set on its body, and
pymunk moves the bodies and resolves contacts; each contact that begins between a
robot and anything is a collision, counted. Every ``1 / rate_hz`` s each robot takes a
lidar scan: the vectorised raycaster, seeded Gaussian noise, ``inf`` for what falls
outside ``range_min..range_max``, then the occlusion mask (``inf``). Lockstep: time
advances only by ``step``; same world and inputs, same output.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import pymunk
from rap_schemas import LaserScan, Odometry, Pose2D, SpinPlan, Twist, pack_ranges

from .executor import PlanExecutor
from .geometry import cast_rays, scene_of
from .kinematics import DiffDrive, Pose2, wrap
from .navigation import MEMORY_RANGE, Navigator, fold_points, near_returns
from .occlusion import occlusion_mask
from .physics import STATIC, static_space
from .world import RobotSpec, WorldSpec, check_world

__all__ = ["Robot", "ScanEvent", "Simulation"]

ROBOT = 2
MASS = 3.3  # kg, a TurtleBot 4
DRIVE_FORCE = 50.0  # N the wheels can push with
DRIVE_TORQUE = 5.0  # N m


@dataclass
class Robot:
    spec: RobotSpec
    body: pymunk.Body
    shape: pymunk.Circle
    control: pymunk.Body
    """Kinematic body the robot is pulled along by, through joints of bounded force:
    the wheels' command, which walls and other robots can overpower."""
    drive: DiffDrive
    nav: Navigator
    executor: PlanExecutor = field(default_factory=PlanExecutor)
    override: tuple[float, float, float] | None = None
    """(v, w, until): a plain velocity command in force until sim time ``until``."""
    last_ranges: npt.NDArray[np.float64] | None = None
    """What navigation sees: the last scan, with remembered obstacles folded in."""
    memory: deque[tuple[float, npt.NDArray[np.float64]]] = field(default_factory=deque)
    """(time, world-frame points) of recent scans' near returns."""
    collisions: int = 0
    distance: float = 0.0
    v: float = 0.0
    w: float = 0.0

    @property
    def pose(self) -> Pose2:
        p = self.body.position
        return Pose2(float(p.x), float(p.y), wrap(float(self.body.angle)))


@dataclass(frozen=True)
class ScanEvent:
    robot: str
    t: float
    scan: LaserScan
    occluded: npt.NDArray[np.bool_]
    """Ground truth: beams covered by an occlusion (never on the robot's topics)."""


class Simulation:
    def __init__(self, world: WorldSpec) -> None:
        """Raises :class:`~sim_world.world.WorldError` for an impossible world (a world
        built in code gets the checks a world file gets)."""
        self.world = check_world(world)
        self.t = 0.0
        self.dt = 1.0 / world.physics_hz
        self.space = static_space(world)
        self.scene = scene_of(world)
        self.rng = np.random.default_rng(world.seed)
        lidar = world.lidar
        self.beam_angles: npt.NDArray[np.float64] = (
            lidar.angle_min + np.arange(lidar.beams, dtype=np.float64) * lidar.angle_increment
        )
        self.scan_period = 1.0 / lidar.rate_hz
        self._next_scan = self.scan_period
        self._ticks = 0
        self.robots: dict[str, Robot] = {}
        for spec in world.robots:
            body = pymunk.Body(MASS, pymunk.moment_for_circle(MASS, 0, spec.radius))
            body.position = (spec.start.x, spec.start.y)
            body.angle = spec.start.theta
            shape = pymunk.Circle(body, spec.radius)
            shape.collision_type = ROBOT
            shape.friction = 0.0
            control = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
            control.position, control.angle = body.position, body.angle
            pivot = pymunk.PivotJoint(control, body, (0, 0), (0, 0))
            pivot.max_bias = 0.0  # follow the control body's velocity, not its position
            pivot.max_force = DRIVE_FORCE
            gear = pymunk.GearJoint(control, body, 0.0, 1.0)
            gear.error_bias = 0.0
            gear.max_bias = 0.0
            gear.max_force = DRIVE_TORQUE
            self.space.add(body, shape, control, pivot, gear)
            self.robots[spec.name] = Robot(
                spec,
                body,
                shape,
                control,
                DiffDrive(spec.wheel_separation, spec.max_linear, spec.max_angular),
                Navigator(spec),
            )
        by_shape = {id(r.shape): r for r in self.robots.values()}

        def begin(arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
            for s in arbiter.shapes:
                robot = by_shape.get(id(s))
                if robot is not None:
                    robot.collisions += 1

        self.space.on_collision(ROBOT, STATIC, begin=begin)
        self.space.on_collision(ROBOT, ROBOT, begin=begin)

    # -- inputs ----------------------------------------------------------------------------

    def set_plan(self, robot: str, plan: SpinPlan) -> None:
        self.robots[robot].executor.apply(plan, self.t)

    def set_velocity(self, robot: str, twist: Twist, duration: float = 0.5) -> None:
        """A plain velocity command, in force for ``duration`` s of sim time."""
        self.robots[robot].override = (twist.linear, twist.angular, self.t + duration)

    # -- stepping --------------------------------------------------------------------------

    def step(self) -> list[ScanEvent]:
        """Advance one physics step; returns the scans taken at the new time."""
        t = self.t
        for r in self.robots.values():
            pose = r.pose
            if r.override is not None and t < r.override[2]:
                v, w = r.override[0], r.override[1]
            else:
                r.override = None
                omega = r.executor.omega(t)
                if omega is not None:
                    v, w = 0.0, omega
                else:
                    v, w = r.nav.command(pose, self.beam_angles, r.last_ranges)
            v, w = r.drive.clamp(v, w)
            r.v, r.w = v, w
            r.control.velocity = (v * math.cos(pose.theta), v * math.sin(pose.theta))
            r.control.angular_velocity = w
        before = {n: r.body.position for n, r in self.robots.items()}
        self.space.step(self.dt)
        for n, r in self.robots.items():
            r.distance += float((r.body.position - before[n]).length)
        self._ticks += 1
        self.t = self._ticks * self.dt
        events: list[ScanEvent] = []
        if self.t + 1e-9 >= self._next_scan:
            self._next_scan += self.scan_period
            events = [self.scan(name) for name in self.robots]
        return events

    def run(self, seconds: float) -> list[ScanEvent]:
        events: list[ScanEvent] = []
        for _ in range(round(seconds / self.dt)):
            events += self.step()
        return events

    # -- sensing ---------------------------------------------------------------------------

    def scan(self, name: str) -> ScanEvent:
        r = self.robots[name]
        pose = r.pose
        lidar = self.world.lidar
        others = np.array(
            [
                (o.body.position.x, o.body.position.y, o.spec.radius)
                for o in self.robots.values()
                if o is not r
            ]
        ).reshape(-1, 3)
        ranges = cast_rays(
            pose.x, pose.y, pose.theta + self.beam_angles, self.scene, lidar.range_max, others
        )
        if lidar.noise_std > 0:
            ranges = ranges + self.rng.normal(0.0, lidar.noise_std, ranges.shape)
        # no return outside range_min..range_max (noise pushes some past either end)
        ranges[(ranges < lidar.range_min) | (ranges > lidar.range_max)] = np.inf
        occluded = occlusion_mask(
            self.world.occlusions, name, self.t, self.beam_angles, self.world.seed
        )
        ranges[occluded] = np.inf
        r.last_ranges = self._remember(r, pose, ranges)
        scan = LaserScan(
            stamp=round(self.t * 1e9),
            frame_id=f"{name}/base_link",
            angle_min=lidar.angle_min,
            angle_increment=lidar.angle_increment,
            range_min=lidar.range_min,
            range_max=lidar.range_max,
            ranges=pack_ranges(ranges),
            scan_time=self.scan_period,
        )
        return ScanEvent(name, self.t, scan, occluded)

    def _remember(
        self, r: Robot, pose: Pose2, ranges: npt.NDArray[np.float64]
    ) -> npt.NDArray[np.float64]:
        """Fold the obstacles seen in the last ``obstacle_memory`` s into ``ranges``."""
        horizon = r.spec.obstacle_memory
        if horizon <= 0:
            return ranges
        pts = near_returns(pose, self.beam_angles, ranges, MEMORY_RANGE)
        mem = r.memory
        while mem and mem[0][0] < self.t - horizon:
            mem.popleft()
        seen = [p for _, p in mem]
        mem.append((self.t, pts))
        if not seen:
            return ranges
        old = np.concatenate(seen)
        if old.size == 0:
            return ranges
        lidar = self.world.lidar
        return fold_points(pose, ranges, old, lidar.angle_min, lidar.angle_increment)

    def odometry(self, name: str) -> Odometry:
        r = self.robots[name]
        p = r.pose
        return Odometry(
            stamp=round(self.t * 1e9),
            frame_id=f"{name}/odom",
            pose=Pose2D(x=p.x, y=p.y, theta=p.theta),
            twist=Twist(linear=r.v, angular=r.w),
        )
