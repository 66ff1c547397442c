"""The lidar case's digital twin: a spin plan rolled out against the robot's belief.

:class:`LidarTwin` is a :class:`rap_sdk.twin.Twin` of kind SIMULATION. ``rollout(plan,
belief)`` runs the plan as the robot's executor would (``sim_world.executor``: at the
start of every period the commands in order, turning in place, then nominal navigation
for the rest) over ``horizon`` periods, from the belief's pose and velocity. Nominal
navigation is sim_world's own :class:`~sim_world.navigation.Navigator`, fed synthetic
scans raycast against the *believed* obstacles only (the belief's
:class:`~lidar_occlusion.belief.ObstacleMap`; never the simulator's world), with the
current lidar mask applied (occluded beams read ``inf``, as on the robot; the mask is
fixed in the robot's frame, so turning moves what is hidden), and with the obstacles
navigation remembers folded in (sim_world's rule: returns within 2.5 m, for
``obstacle_memory`` s; the map says which cells the robot saw that near, and when).
Motion is sim_world's :class:`~sim_world.kinematics.DiffDrive` (exact unicycle steps).

The report (:class:`~rap_sdk.twin.TwinReport`):

- reject ``belief``: a belief with a non-finite pose, velocity or time (not rolled out);
- reject ``limits``: a non-finite or negative number (not rolled out at all), a turn
  rate beyond ``max_angular``, commands that do not fit in the period, a period beyond
  ``max_period``;
- reject ``collision``: the robot's disc meets a believed obstacle (when, where);
  ``clearance``: it comes nearer than ``min_clearance`` without touching;
- reject ``spec:<output>``: an output of the robot-state trust spec
  (``specs/robot_state.dsrv``, run over the rollout's steps) turned false;
- note ``near-miss``: the clearance came below ``near_miss``;
- note ``thin-belief``: the way ahead within the horizon crosses space the robot has not
  looked at in the last ``thin_within`` s (``BeliefQuality.thin``): an approval then
  says only that what the robot knows of is avoided.

Metrics: ``min_clearance_m`` (capped at ``clearance_cap``), ``spin_s``, ``progress_m``
(distance made good along the route), ``collisions`` (contacts begun), ``steps``, and
where the robot ends: ``end_x_m``, ``end_y_m``, ``end_theta`` (world frame).

:func:`pose_mismatch` is the check that a plan was made for this robot at about this
pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources

import msgspec
import numpy as np
import numpy.typing as npt
from rap_schemas import Pose2D, SpinPlan
from rap_sdk.twin import BeliefQuality, Finding, TwinKind, TwinReport
from sim_world.executor import PlanExecutor
from sim_world.kinematics import DiffDrive, Pose2, wrap
from sim_world.navigation import LOOKAHEAD, MARGIN, MEMORY_RANGE, Navigator, fold_points
from sim_world.world import Point, Pose, RobotSpec
from trust_checker import Explainer, SpecRunner, load_spec
from trust_checker.lang import ast

from .belief import LidarBelief

__all__ = [
    "LidarTwin",
    "TwinConfig",
    "limits",
    "pose_mismatch",
    "robot_state_spec",
]

F = npt.NDArray[np.float64]


class TwinConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The twin's robot model, checks and resolution; a value out of range raises
    ``ValueError`` naming it."""

    horizon: int = 1
    """Plan periods rolled out."""
    min_clearance: float = 0.05
    """Metres the robot's disc must keep from believed obstacles (``clearance``)."""
    near_miss: float = 0.15
    """Below this clearance (m) a ``near-miss`` note is given."""
    max_angular: float = 1.9
    """The robot's turn-rate limit, rad/s."""
    max_linear: float = 0.31
    """The robot's top speed, m/s."""
    wheel_separation: float = 0.233
    max_period: float = 30.0
    """The longest plan period accepted, s (a longer one spins too rarely to help)."""
    obstacle_memory: float = 10.0
    """Seconds the robot's navigation remembers near obstacles (sim_world's robot
    field of the same name; 0: none)."""
    step: float = 0.1
    """Seconds per rollout step."""
    scan_hz: float = 5.0
    """Synthetic scans per second of rollout (the robot's lidar rate)."""
    beams: int = 90
    """Beams per synthetic scan (the robot has 360; navigation needs fewer)."""
    view_range: float = MEMORY_RANGE
    """Metres a synthetic scan reaches: navigation looks 0.9 m ahead and remembers
    returns within 2.5 m, so nothing farther changes what the robot does."""
    max_accel: float = 15.0
    """m/s^2: how fast the speed may change from the belief's (sim_world's drive: 50 N
    on 3.3 kg)."""
    max_angular_accel: float = 100.0
    """rad/s^2, the same for turning."""
    thin_within: float = 10.0
    """Seconds within which a place must have been looked at not to count as thin."""
    clearance_cap: float = 1.0
    """``min_clearance_m`` reads at most this (m): obstacles farther are not measured."""
    max_shift: float = 0.25
    """Metres between the pose a plan was made for and the current one, at most."""
    max_turn: float = 0.5
    """Radians of heading between them, at most."""
    trust: bool = True
    """Run the robot-state trust spec over the rollout (a few µs a step)."""

    def __post_init__(self) -> None:
        positive = (
            "min_clearance",
            "near_miss",
            "max_angular",
            "max_linear",
            "wheel_separation",
            "max_period",
            "step",
            "scan_hz",
            "view_range",
            "max_accel",
            "max_angular_accel",
            "thin_within",
            "clearance_cap",
            "max_shift",
            "max_turn",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"TwinConfig.{name} = {value!r}: give a finite number > 0")
        if not (math.isfinite(self.obstacle_memory) and self.obstacle_memory >= 0):
            raise ValueError(
                f"TwinConfig.obstacle_memory = {self.obstacle_memory!r}: give seconds >= 0"
            )
        if not 1 <= self.horizon <= 100:
            raise ValueError(f"TwinConfig.horizon = {self.horizon!r}: give 1 to 100 periods")
        if not 8 <= self.beams <= 3600:
            raise ValueError(f"TwinConfig.beams = {self.beams!r}: give 8 to 3600 beams")
        if self.scan_hz * self.step > 1.0 + 1e-9:
            raise ValueError(
                f"TwinConfig.scan_hz = {self.scan_hz} with step = {self.step} s scans more "
                "than once a step; make the step at most 1 / scan_hz"
            )


def robot_state_spec() -> str:
    """The text of the robot-state trust spec (``lidar_occlusion/specs/robot_state.dsrv``)."""
    return (
        resources.files("lidar_occlusion")
        .joinpath("specs", "robot_state.dsrv")
        .read_text(encoding="utf-8")
    )


def limits(plan: SpinPlan, cfg: TwinConfig) -> tuple[list[Finding], bool]:
    """The ``limits`` findings of ``plan``, and whether it can be rolled out at all
    (False for a non-finite or negative number)."""
    out: list[Finding] = []
    period = plan.period
    if not (math.isfinite(period) and period > 0):
        msg = f"period {period} s is not a positive number"
        return [Finding(code="limits", message=msg)], False
    total = 0.0
    for i, c in enumerate(plan.commands):
        if not (math.isfinite(c.omega) and math.isfinite(c.duration)) or c.duration < 0:
            msg = f"command {i} cannot be executed: omega {c.omega} rad/s, duration {c.duration} s"
            return [Finding(code="limits", message=msg)], False
        if abs(c.omega) > cfg.max_angular:
            out.append(
                Finding(
                    code="limits",
                    message=f"command {i} turns at {c.omega} rad/s, beyond the robot's "
                    f"limit of {cfg.max_angular} rad/s",
                )
            )
        total += c.duration
    if plan.commands and total >= period:
        out.append(
            Finding(
                code="limits",
                message=f"commands take {total:.3f} s, not within the period of {period} s",
            )
        )
    if period > cfg.max_period:
        out.append(
            Finding(
                code="limits",
                message=f"period {period} s is beyond the longest accepted, {cfg.max_period} s",
            )
        )
    return out, True


def pose_mismatch(
    planned_for: Pose2D,
    now: Pose2D,
    robot: str,
    planned_robot: str,
    cfg: TwinConfig | None = None,
) -> Finding | None:
    """A ``pose-mismatch`` finding (reject) when a plan made for ``planned_robot`` at
    ``planned_for`` is about to run on ``robot``, now at ``now``, and they are not the
    same robot, or the pose moved more than ``max_shift`` m or turned more than
    ``max_turn`` rad since; None when it fits."""
    c = cfg or TwinConfig()
    if robot != planned_robot:
        return Finding(
            code="pose-mismatch",
            message=f"the plan was made for robot {planned_robot!r}, not {robot!r}",
        )
    shift = math.hypot(now.x - planned_for.x, now.y - planned_for.y)
    turn = abs(wrap(now.theta - planned_for.theta))
    if not (shift <= c.max_shift and turn <= c.max_turn):  # NaN fails too
        return Finding(
            code="pose-mismatch",
            message=f"the plan was made at ({planned_for.x:.2f}, {planned_for.y:.2f}, "
            f"{planned_for.theta:.2f} rad); {robot} is at ({now.x:.2f}, {now.y:.2f}, "
            f"{now.theta:.2f} rad): {shift:.2f} m and {turn:.2f} rad away, beyond "
            f"{c.max_shift} m or {c.max_turn} rad",
        )
    return None


@dataclass(frozen=True)
class _Trace:
    t: F
    pose: F
    """(T, 3): x, y, theta at each step's start, then the end."""
    v: F
    w_cmd: F
    """Per step: the turn rate commanded: the plan's (as asked), or navigation's (within
    the base's limit, as the robot's drive applies it)."""
    spin: npt.NDArray[np.bool_]
    progress: float


class LidarTwin:
    """``rollout(plan, belief)``: see the module. Stateless between rollouts (one twin may
    serve several threads)."""

    kind = TwinKind.SIMULATION

    def __init__(self, config: TwinConfig | None = None, *, spec: str | None = None) -> None:
        """``spec``: the text of a trust spec with Float inputs ``clearance`` and
        ``omega`` to run instead of the shipped robot-state spec (``config.trust``)."""
        self.config = config or TwinConfig()
        self.spec: ast.Spec | None = None
        if self.config.trust:
            self.spec = load_spec(spec if spec is not None else robot_state_spec())

    # -- the rollout -----------------------------------------------------------------------

    def rollout(self, plan: SpinPlan, belief: LidarBelief) -> TwinReport:
        cfg = self.config
        findings, executable = limits(plan, cfg)
        if not executable:
            return TwinReport(
                kind=self.kind,
                horizon_s=0.0,
                findings=findings,
                belief=BeliefQuality(thin=True, notes=["the plan was not rolled out"]),
            )
        p = belief.pose
        state = (p.x, p.y, p.theta, belief.v, belief.w, belief.t, belief.radius)
        if not all(math.isfinite(x) for x in state) or belief.radius <= 0:
            msg = (
                f"the belief of {belief.robot} is not usable: pose ({p.x}, {p.y}, {p.theta}), "
                f"velocity ({belief.v}, {belief.w}), time {belief.t}, radius {belief.radius}"
            )
            return TwinReport(
                kind=self.kind,
                horizon_s=0.0,
                findings=[*findings, Finding(code="belief", message=msg)],
                belief=BeliefQuality(thin=True, notes=["the plan was not rolled out"]),
            )
        horizon_s = cfg.horizon * min(plan.period, cfg.max_period)
        world = _Believed(belief, cfg, horizon_s)
        trace = world.run(plan, horizon_s)
        clear, nearest = world.clearance(trace.pose)
        metrics: dict[str, float] = {
            "min_clearance_m": round(float(clear.min()), 4),
            "spin_s": round(float(np.count_nonzero(trace.spin)) * horizon_s / trace.spin.size, 3),
            "progress_m": round(trace.progress, 3),
            "collisions": 0.0,
            "steps": float(trace.v.size),
            "end_x_m": round(float(trace.pose[-1, 0]), 4),
            "end_y_m": round(float(trace.pose[-1, 1]), 4),
            "end_theta": round(float(trace.pose[-1, 2]), 4),
        }
        findings += self._contact(trace, clear, nearest, belief, metrics)
        if self.spec is not None:
            findings += self._spec(trace, clear)
        quality = self._thin(trace, belief)
        if quality.thin:
            findings.append(Finding(code="thin-belief", message=quality.notes[0], severity="note"))
        return TwinReport(
            kind=self.kind, horizon_s=horizon_s, findings=findings, metrics=metrics, belief=quality
        )

    def _contact(
        self,
        trace: _Trace,
        clear: F,
        nearest: F,
        belief: LidarBelief,
        metrics: dict[str, float],
    ) -> list[Finding]:
        cfg = self.config
        touching = clear < 0
        begun = touching & ~np.concatenate([[False], touching[:-1]])
        metrics["collisions"] = float(np.count_nonzero(begun))
        if touching.any():
            k = int(np.argmax(touching))
            x, y = trace.pose[k, 0], trace.pose[k, 1]
            ox, oy = nearest[k]
            return [
                Finding(
                    code="collision",
                    message=f"{belief.robot}'s disc (radius {belief.radius} m) meets a believed "
                    f"obstacle at ({ox:.2f}, {oy:.2f}) {trace.t[k]:.1f} s into the horizon, "
                    f"the robot at ({x:.2f}, {y:.2f}); {int(metrics['collisions'])} "
                    "contact(s) begun",
                    at_s=float(trace.t[k]),
                )
            ]
        low = float(clear.min())
        k = int(np.argmin(clear))
        where = (
            f"{trace.t[k]:.1f} s into the horizon, at ({trace.pose[k, 0]:.2f}, "
            f"{trace.pose[k, 1]:.2f}), from the believed obstacle at "
            f"({nearest[k, 0]:.2f}, {nearest[k, 1]:.2f})"
        )
        if low < cfg.min_clearance:
            return [
                Finding(
                    code="clearance",
                    message=f"clearance {low:.3f} m, below the minimum {cfg.min_clearance} m, "
                    + where,
                    at_s=float(trace.t[k]),
                )
            ]
        if low < cfg.near_miss:
            return [
                Finding(
                    code="near-miss",
                    message=f"clearance {low:.3f} m (minimum {cfg.min_clearance} m), " + where,
                    severity="note",
                    at_s=float(trace.t[k]),
                )
            ]
        return []

    def _spec(self, trace: _Trace, clear: F) -> list[Finding]:
        """The spec over the rollout's steps; a verdict per output that turned false (and
        per trigger that fired), the first of each, explained."""
        assert self.spec is not None
        ticks = [
            {"clearance": float(clear[k]), "omega": float(trace.w_cmd[k])}
            for k in range(trace.w_cmd.size)
        ]
        runner = SpecRunner(self.spec)
        bools = {d.name for d in self.spec.decls if d.kind == "out" and d.type == ast.TName("Bool")}
        false_at: dict[str, int] = {}
        last: dict[str, object] = {}
        fired = False
        for k, inputs in enumerate(ticks):  # the plain runner first: cheap, no verdicts
            for o in runner.step(inputs):
                if o.stream in bools and o.value is False and last.get(o.stream) is not False:
                    false_at.setdefault(o.stream, k)
                last[o.stream] = o.value
            fired = fired or bool(runner.fired)
        if not false_at and not fired:
            return []
        explainer = Explainer(SpecRunner(self.spec))  # again, explained
        out: list[Finding] = []
        done: set[str] = set()
        for k, inputs in enumerate(ticks):
            for v in explainer.step(inputs, round(float(trace.t[k]) * 1e9)).verdicts:
                if v.stream in done:
                    continue
                done.add(v.stream)
                reject = v.kind != "trigger" or v.severity in ("error", "critical")
                out.append(
                    Finding(
                        code=f"spec:{v.stream}",
                        message=f"{v.describe().splitlines()[0]} at {trace.t[k]:.1f} s "
                        f"into the horizon (clearance {clear[k]:.3f} m, omega "
                        f"{trace.w_cmd[k]:.3f} rad/s)",
                        severity="reject" if reject else "note",
                        at_s=float(trace.t[k]),
                    )
                )
        return out

    def _thin(self, trace: _Trace, belief: LidarBelief) -> BeliefQuality:
        """Thin when a place the robot's disc would cross (or face, one radius ahead,
        while driving) was not looked at within ``thin_within`` s."""
        cfg = self.config
        pose = trace.pose[:-1]
        moving = np.abs(trace.v) > 1e-6
        ahead = belief.radius + MARGIN
        front = np.column_stack(
            (
                pose[moving, 0] + ahead * np.cos(pose[moving, 2]),
                pose[moving, 1] + ahead * np.sin(pose[moving, 2]),
            )
        )
        pts = np.vstack([trace.pose[:, :2], front])
        when = np.concatenate([trace.t, trace.t[:-1][moving]])
        seen = belief.map.looked_recently(pts, belief.t, cfg.thin_within)
        if seen.all():
            return BeliefQuality()
        first = int(np.argmin(np.where(seen, np.inf, when)))
        unseen = int(np.count_nonzero(~seen))
        note = (
            f"the way ahead crosses space not looked at in the last {cfg.thin_within:g} s: "
            f"{unseen} of {seen.size} points of the path, the first at "
            f"({pts[first, 0]:.2f}, {pts[first, 1]:.2f}) {when[first]:.1f} s into the "
            "horizon; the twin knows no obstacle there, the robot may find one"
        )
        return BeliefQuality(thin=True, notes=[note])


class _Believed:
    """The belief as the rollout sees it: obstacle points near the robot, the mask on the
    twin's beams, what navigation remembers."""

    def __init__(self, belief: LidarBelief, cfg: TwinConfig, horizon_s: float) -> None:
        self.belief, self.cfg = belief, cfg
        self.inc = 2 * math.pi / cfg.beams
        self.angle_min = belief.angle_min
        self.angles: F = self.angle_min + np.arange(cfg.beams, dtype=np.float64) * self.inc
        self.occluded = self._mask()
        m = belief.map
        p = belief.pose
        pts = m.obstacles()
        # what the robot could reach within the horizon, and see or measure from there
        reach = cfg.max_linear * horizon_s + cfg.view_range + cfg.clearance_cap + belief.radius
        keep = np.hypot(pts[:, 0] - p.x, pts[:, 1] - p.y) < reach
        self.pts: F = pts[keep]
        self.half_cell = m.cell / 2
        self.blocking = math.hypot(LOOKAHEAD, belief.radius + MARGIN)
        # what navigation remembers: seconds (rollout time) each cell was last seen near
        self.near_t: F = -m.near_ages(belief.t)[keep]

    def _mask(self) -> npt.NDArray[np.bool_]:
        """Twin beam ``j`` is occluded when a mask beam nearest to it, or one it is the
        nearest twin beam of, is."""
        out = np.zeros(self.cfg.beams, dtype=bool)
        mask = self.belief.mask
        if mask is None or mask.beams == 0:
            return out
        flags = np.asarray(mask.flags(), dtype=bool)
        n = flags.size
        mask_angles = mask.angle_min + np.arange(n, dtype=np.float64) * mask.angle_increment
        to_twin = np.rint((mask_angles - self.angle_min) / self.inc).astype(np.intp)
        out[to_twin[flags] % self.cfg.beams] = True
        to_mask = np.rint((self.angles - mask.angle_min) / mask.angle_increment).astype(np.intp)
        out |= flags[to_mask % n]
        return out

    def scan(self, pose: Pose2) -> tuple[F, npt.NDArray[np.intp]]:
        """Ranges of a synthetic scan at ``pose`` (``inf``: no believed obstacle within
        ``view_range``, or an occluded beam), and the indices of the cells it returned
        from. Each cell is a z-buffered arc: the beams within its angular half-width
        (the nearest beam for a cell between two), at its centre's distance."""
        n = self.cfg.beams
        out = np.full(n, np.inf)
        dx, dy = self.pts[:, 0] - pose.x, self.pts[:, 1] - pose.y
        d = np.hypot(dx, dy)
        sel = np.flatnonzero((d < self.cfg.view_range) & (d > 1e-9))
        if sel.size == 0:
            return out, sel
        d = d[sel]
        rel = (np.arctan2(dy[sel], dx[sel]) - (pose.theta + self.angle_min)) / self.inc
        half = np.arctan2(self.half_cell, d) / self.inc
        lo = np.ceil(rel - half)
        hi = np.floor(rel + half)
        between = hi < lo  # a cell between two beams: its nearest beam
        nearest = np.rint(rel)
        lo = np.where(between, nearest, lo)
        reps = (np.where(between, nearest, hi) - lo + 1).clip(1, n).astype(np.intp)
        cell = np.repeat(np.arange(sel.size), reps)
        beam = (lo[cell] + np.arange(cell.size) - (np.cumsum(reps) - reps)[cell]).astype(np.intp)
        beam %= n
        dist = d[cell]
        np.minimum.at(out, beam, dist)
        out[self.occluded] = np.inf
        shown = np.zeros(sel.size, dtype=bool)
        got = out[beam]
        shown[cell[np.isfinite(got) & (dist <= got)]] = True  # occluded beams show nothing
        return out, sel[shown]

    def run(self, plan: SpinPlan, horizon_s: float) -> _Trace:
        cfg, b = self.cfg, self.belief
        steps = max(1, round(horizon_s / cfg.step))
        dt = horizon_s / steps
        spec = RobotSpec(
            name=b.robot,
            start=Pose(x=b.pose.x, y=b.pose.y, theta=b.pose.theta),
            route=[Point(x=x, y=y) for x, y in b.route],
            radius=b.radius,
            wheel_separation=cfg.wheel_separation,
            max_linear=cfg.max_linear,
            max_angular=cfg.max_angular,
            loop_route=b.loop_route,
            obstacle_memory=cfg.obstacle_memory,
        )
        nav = Navigator(spec)
        nav.index = _waypoint(b)
        drive = DiffDrive(cfg.wheel_separation, cfg.max_linear, cfg.max_angular)
        executor = PlanExecutor()
        executor.apply(plan, 0.0)
        pose = Pose2(b.pose.x, b.pose.y, wrap(b.pose.theta))
        v, w = b.v, b.w
        poses = np.empty((steps + 1, 3))
        times = np.arange(steps + 1, dtype=np.float64) * dt
        vs, ws = np.empty(steps), np.empty(steps)
        spin = np.zeros(steps, dtype=bool)
        scan_every = max(1, round(1.0 / (cfg.scan_hz * dt)))
        ranges = self._navigation_scan(pose, 0.0)
        progress = 0.0
        route = b.route
        for k in range(steps):
            t = k * dt
            if k and k % scan_every == 0:
                ranges = self._navigation_scan(pose, t)
            poses[k] = pose.x, pose.y, pose.theta
            omega = executor.omega(t)
            if omega is not None:
                v_cmd, w_cmd = 0.0, omega
                spin[k] = True
                ws[k] = omega  # what the plan asks for
                v_cmd, w_cmd = drive.clamp(v_cmd, w_cmd)
            else:
                v_cmd, w_cmd = drive.clamp(*nav.command(pose, self.angles, ranges))
                ws[k] = w_cmd  # navigation's, within the base's limit as on the robot
            dv, dw = cfg.max_accel * dt, cfg.max_angular_accel * dt
            v = min(max(v_cmd, v - dv), v + dv)
            w = min(max(w_cmd, w - dw), w + dw)
            vs[k] = v
            new = drive.step(pose, v, w, dt)
            if route and not nav.done:
                tx, ty = route[nav.index % len(route)]
                progress += math.hypot(tx - pose.x, ty - pose.y) - math.hypot(
                    tx - new.x, ty - new.y
                )
            pose = new
        poses[steps] = pose.x, pose.y, pose.theta
        return _Trace(t=times, pose=poses, v=vs, w_cmd=ws, spin=spin, progress=progress)

    def _navigation_scan(self, pose: Pose2, t: float) -> F:
        """A synthetic scan as navigation sees it: the remembered cells folded in, and
        the cells this scan returned from within ``MEMORY_RANGE`` remembered from now."""
        ranges, shown = self.scan(pose)
        memory = self.cfg.obstacle_memory
        if memory <= 0:
            return ranges
        remembered = self.near_t >= t - memory
        out = fold_points(pose, ranges, self.pts[remembered], self.angle_min, self.inc)
        if shown.size:
            near = np.hypot(self.pts[shown, 0] - pose.x, self.pts[shown, 1] - pose.y)
            self.near_t[shown[near < MEMORY_RANGE]] = t
        # a return this far can block no heading (the Navigator's corridor is LOOKAHEAD
        # long and radius + MARGIN wide): leaving it out changes no command, and saves
        # the Navigator most of its work
        out[out >= self.blocking] = np.inf
        return out

    def clearance(self, poses: F) -> tuple[F, F]:
        """Per pose: metres between the robot's disc and the nearest believed obstacle
        (a cell as a disc of the cell's diameter; capped at ``clearance_cap``), and where
        that obstacle is (NaN when none is within the cap)."""
        cap = self.cfg.clearance_cap
        r = self.belief.radius + self.half_cell
        lo = poses[:, :2].min(axis=0) - (r + cap)
        hi = poses[:, :2].max(axis=0) + (r + cap)
        pts = self.pts
        near = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
        if near.shape[0] == 0:
            return np.full(poses.shape[0], cap), np.full((poses.shape[0], 2), np.nan)
        d = np.hypot(poses[:, None, 0] - near[None, :, 0], poses[:, None, 1] - near[None, :, 1])
        i = np.argmin(d, axis=1)
        clear = np.minimum(d[np.arange(d.shape[0]), i] - r, cap)
        where = np.where((clear < cap)[:, None], near[i], np.nan)
        return clear, where


def _waypoint(b: LidarBelief) -> int:
    """The belief's waypoint, else the one ending the route segment nearest the robot
    (the segment into waypoint 0 starts at the last one on a looped route, else it is
    waypoint 0 itself)."""
    n = len(b.route)
    if b.waypoint is not None or n == 0:
        return b.waypoint or 0
    p = np.array([b.pose.x, b.pose.y])
    w = np.asarray(b.route, dtype=np.float64)
    a = np.roll(w, 1, axis=0)
    if not b.loop_route:
        a[0] = w[0]
    seg = w - a
    length2 = np.einsum("ij,ij->i", seg, seg)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.clip(np.einsum("ij,ij->i", p - a, seg) / length2, 0.0, 1.0)
    u = np.where(length2 > 0, u, 1.0)
    closest = a + u[:, None] * seg - p
    return int(np.argmin(np.hypot(closest[:, 0], closest[:, 1])))
