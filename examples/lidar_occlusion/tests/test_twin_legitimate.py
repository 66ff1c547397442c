"""The twin-backed Legitimate stage on the fabric: the monitor builds the robot's belief from
its scans and odometry, and every planted unsafe plan is rejected with the twin's finding in
``plan-rejected``, while a plan that looks at what hides the way ahead is approved."""

from __future__ import annotations

import math
import time

import numpy as np
import numpy.typing as npt
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from lidar_occlusion.nodes import LIDAR_MASK, PLANNED_FOR, MonitorConfig, build
from lidar_occlusion.planning import LegitimacyConfig
from rap_schemas import (
    LaserScan,
    LidarMask,
    Odometry,
    PlanProposal,
    Pose2D,
    SpinCommand,
    SpinPlan,
    Twist,
    Verdict,
    keys,
    pack_flags,
    pack_ranges,
)
from rap_sdk.knowledge import KnowledgeClient
from rap_sdk.testing import Harness
from sim_world.geometry import cast_rays, scene_of
from sim_world.world import Circle, Pose, RobotSpec, Room, WorldSpec

pytestmark = pytest.mark.anyio

SYSTEM = "twin"
N = 360
INC = 2 * math.pi / N
BEAMS = -math.pi + np.arange(N) * INC
SCENE = scene_of(
    WorldSpec(
        room=Room(width=10.0, height=8.0),
        obstacles=[Circle(x=3.6, y=4.0, r=0.3)],
        robots=[RobotSpec(name="tb1", start=Pose(x=1.0, y=4.0))],
    )
)
BACK = Pose2D(x=0.5, y=4.0, theta=0.0)
HERE = Pose2D(x=1.0, y=4.0, theta=0.0)
FRONT = np.mod(BEAMS + 0.7, 2 * math.pi) < 1.4  # the front sector, hidden at HERE


def _scan(pose: Pose2D, t: float, hidden: npt.NDArray[np.bool_] | None) -> LaserScan:
    r = cast_rays(pose.x, pose.y, pose.theta + BEAMS, SCENE, 12.0)
    if hidden is not None:
        r[hidden] = np.inf
    return LaserScan(
        stamp=round(t * 1e9),
        frame_id="tb1/base_link",
        angle_min=-math.pi,
        angle_increment=INC,
        range_min=0.1,
        range_max=12.0,
        ranges=pack_ranges(r),
    )


def _odom(pose: Pose2D, t: float, robot: str = "tb1") -> Odometry:
    return Odometry(
        stamp=round(t * 1e9),
        frame_id=f"{robot}/odom",
        pose=pose,
        twist=Twist(linear=0.0, angular=0.0),
    )


def _spin(*commands: tuple[float, float], period: float = 8.0) -> SpinPlan:
    return SpinPlan(commands=[SpinCommand(omega=w, duration=d) for w, d in commands], period=period)


async def test_the_twin_rejects_every_planted_unsafe_plan() -> None:
    loop = build(
        "tb1",
        monitoring=MonitorConfig(belief=True),
        legitimacy=LegitimacyConfig(twin=True, route=[(8.0, 4.0)], loop_route=False),
    )
    async with Harness(system=SYSTEM) as h:
        await h.hold(open_service(KnowledgeConfig(system=SYSTEM), fabric=h.fabric))
        kb = await h.hold(KnowledgeClient(fabric=h.fabric, system=SYSTEM, writer="analysis"))
        await h.start(loop.monitor, loop.legitimate)
        # the robot sends odometry: each scan then waits for the pose of its stamp
        await h.publish("tb1/odom", _odom(BACK, 0.0))
        # the robot saw the obstacle from 3 m away, then something hid its front sector
        for pose, t, hidden in ((BACK, 0.0, None), (HERE, 1.6, FRONT)):
            mark = len(h.records)
            await h.publish("tb1/scan", _scan(pose, t, hidden))
            await h.publish("tb1/odom", _odom(pose, t))
            await h.wait_for(lambda r: r.name == "obstacle_map", after=mark)
        mask = LidarMask(angle_min=-math.pi, angle_increment=INC, occluded=pack_flags(FRONT))
        await kb.write(LIDAR_MASK, mask, durable=True)

        async def judge(plan: SpinPlan, planned_for: Odometry | None = None) -> Verdict[SpinPlan]:
            await kb.write(PLANNED_FOR, planned_for or _odom(HERE, 1.6), durable=True)
            proposal = PlanProposal(
                plan_uid=np.random.default_rng().bytes(16),
                plan_type=plan.TYPE,
                plan=plan,
                proposer="planner",
                created=time.time_ns(),
            )
            mark = len(h.records)
            await h.emit("new-plan", proposal)
            rec = await h.wait_for(
                lambda r: (
                    r.kind is keys.Kind.EVENT
                    and r.name == "verdict"
                    and r.decode(Verdict[SpinPlan]).plan_uid == proposal.plan_uid
                ),
                after=mark,
            )
            return rec.decode(Verdict[SpinPlan])

        # a spin that looks at the hidden obstacle before driving on: approved
        looked = await judge(_spin((1.0, 2 * math.pi)))
        assert looked.approved, looked.reason
        planted = {
            "no look, straight into the obstacle it saw": (_spin(), None, "collision: "),
            "faster than the robot turns": (_spin((3.0, 1.0)), None, "beyond the robot's limit"),
            "longer than its period": (_spin((1.0, 8.5)), None, "not within the period"),
            "a period beyond the limits": (_spin((1.0, 6.3), period=60.0), None, "limits: "),
            "made for another robot": (
                _spin((1.0, 2 * math.pi)),
                _odom(HERE, 1.6, "tb2"),
                "pose-mismatch: ",
            ),
            "made at another pose": (
                _spin((1.0, 2 * math.pi)),
                _odom(Pose2D(x=5.0, y=2.0, theta=1.0), 1.6),
                "pose-mismatch: ",
            ),
        }
        for what, (plan, made_for, reason) in planted.items():
            for _ in range(3):  # every time
                verdict = await judge(plan, made_for)
                assert not verdict.approved, what
                assert reason in (verdict.reason or ""), (what, verdict.reason)
        rejected = [r.decode(Verdict[SpinPlan]) for r in h.of(keys.Kind.EVENT, "plan-rejected")]
        assert len(rejected) == 3 * len(planted)
        assert not h.rejections()
