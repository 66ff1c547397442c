"""The ship simulator on the fabric: the managed system's sensors.

Of system ``S``, every ``sample_period`` s of sim time:

    rap/S/data/ship/pose       Pose: position, heading, velocities, rudder, propeller  (out)
    rap/S/data/ship/weather    Weather: wind, current and waves acting now             (out)

The ship follows its route on its own autopilot (:class:`~ship_motion.physics.RouteFollower`):
the loop adapts the ship's predictor, not its course. Ground truth (every state) stays in
:attr:`ShipService.states` for evaluation code.

Clocks, as the lidar case's simulator: lockstep (``realtime_factor=None``) steps as fast as
the host allows and, given ``sync`` (a :class:`~rap_sdk.cycles.CycleTracker`), waits after
each sample until the cycle it started is over; real time sleeps to keep sim time at
``realtime_factor`` x wall time.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import anyio
import anyio.lowlevel
from anyio.abc import TaskStatus
from rap_schemas import keys
from rap_sdk import Fabric, Node, NodeRuntime
from rap_sdk.cycles import CycleTracker
from rap_sdk.knowledge import KnowledgeClient

from . import messages
from .loop import history_of
from .physics import History, RouteFollower, ScenarioSpec, ShipSimulator, ShipState, Weather

__all__ = [
    "NODE",
    "POSE",
    "WEATHER",
    "ShipService",
    "pose_history",
    "pose_message",
    "state_of",
    "weather_message",
]

log = logging.getLogger(__name__)

NODE = "simulator"
"""The simulator's node name: the model's external component ``simulator``."""
POSE = "ship/pose"
WEATHER = "ship/weather"
MAX_REALTIME_FACTOR = 10_000.0


def pose_message(s: ShipState) -> messages.Pose:
    return messages.Pose(
        t=s.t, x=s.x, y=s.y, psi=s.psi, u=s.u, v=s.v, r=s.r, rudder=s.rudder, rps=s.rps
    )


def state_of(p: messages.Pose) -> ShipState:
    return ShipState(
        t=p.t, x=p.x, y=p.y, psi=p.psi, u=p.u, v=p.v, r=p.r, rudder=p.rudder, rps=p.rps
    )


def weather_message(w: Weather) -> messages.Weather:
    return messages.Weather(
        t=w.t,
        wind_speed=w.wind_speed,
        wind_direction=w.wind_direction,
        current_speed=w.current_speed,
        current_direction=w.current_direction,
        wave_height=w.wave_height,
        wave_direction=w.wave_direction,
    )


class ShipService:
    def __init__(
        self,
        spec: ScenarioSpec,
        *,
        fabric: Fabric,
        system: str,
        realtime_factor: float | None = None,
        sync: CycleTracker | None = None,
        sync_timeout: float = 5.0,
        on_sample: Callable[[ShipState, Weather], None] | None = None,
    ) -> None:
        if realtime_factor is not None and not (
            math.isfinite(realtime_factor) and 0 < realtime_factor <= MAX_REALTIME_FACTOR
        ):
            raise ValueError(
                f"realtime_factor {realtime_factor!r}: give a number > 0 and at most "
                f"{MAX_REALTIME_FACTOR:g}, or None for lockstep"
            )
        self.spec = spec
        self.sim = ShipSimulator(spec)
        self.follower = RouteFollower(spec.route)
        self.fabric = fabric
        self.system = system
        self.realtime_factor = realtime_factor
        self.sync = sync
        self.sync_timeout = sync_timeout
        self.on_sample = on_sample
        self.node = Node(NODE)
        self.states: list[ShipState] = []
        self.lost_cycles = 0
        """Samples whose cycle was not over within ``sync_timeout`` (lockstep only)."""
        self.finished = anyio.Event()

    async def run(
        self,
        duration: float | None = None,
        *,
        task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED,
    ) -> None:
        """Simulate ``duration`` s of sim time (None: the scenario's duration)."""
        spec, sim = self.spec, self.sim
        end = spec.duration_s if duration is None else sim.t + duration
        rt = NodeRuntime(self.node, fabric=self.fabric, system=self.system)
        pose_key = keys.data(self.system, POSE)
        weather_key = keys.data(self.system, WEATHER)
        every = spec.steps_per_sample
        async with anyio.create_task_group() as tg:
            await tg.start(rt.run)
            task_status.started()
            start, t0 = anyio.current_time(), sim.t
            state = sim.state()
            k = 0
            while True:
                if k % every == 0:
                    weather = sim.weather()
                    self.states.append(state)
                    if self.on_sample is not None:
                        self.on_sample(state, weather)
                    env = await rt.send(pose_key, pose_message(state))
                    await rt.send(
                        weather_key, weather_message(weather), cycle=env.uid, cause=env.uid
                    )
                    if self.sync is not None and self.realtime_factor is None:
                        self.sync.expect(env.uid, pose_key)
                        self.sync.expect(env.uid, weather_key)
                        if not await self.sync.wait(env.uid, self.sync_timeout):
                            self.lost_cycles += 1
                if sim.t + 1e-9 >= end:
                    break
                sim.step(self.follower.command(state, spec.dt))
                state = sim.state()
                k += 1
                if self.realtime_factor is None:
                    if k % every == 0:
                        await anyio.lowlevel.checkpoint()
                else:
                    due = start + (sim.t - t0) / self.realtime_factor
                    await anyio.sleep(max(0.0, due - anyio.current_time()))
            rt.stop()
        self.finished.set()


async def pose_history(kb: KnowledgeClient, since: float, key: str = "ship_pose") -> History:
    """The ship's poses from knowledge's history of ``key``, from sim time ``since`` on."""
    records = await kb.history(key, messages.Pose, limit=100_000)
    return history_of(
        [state_of(r.value) for r in records if r.value is not None and r.value.t >= since]
    )
