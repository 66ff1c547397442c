"""What a simulator run is set up with (the command line sets every field).

    config = SimConfig(world="corridor", lockstep=True, duration=60.0)
    async with open_service(config, fabric=fabric) as service:   # sim_world.service
        await service.finished.wait()

A value out of range raises :class:`SimConfigError` on construction (and a
``msgspec.ValidationError`` when the config is decoded), naming the field, the value and
what it may be.
"""

from __future__ import annotations

import math

import msgspec
from rap_schemas import keys

__all__ = ["MAX_DURATION", "MAX_REALTIME_FACTOR", "SimConfig", "SimConfigError"]

MAX_REALTIME_FACTOR = 1e6
"""The largest real-time factor (the bound of ``SimTime.realtime_factor``)."""
MAX_DURATION = 1e9
"""The longest run, in seconds of sim time (stamps stay well inside 64-bit nanoseconds)."""


class SimConfigError(ValueError):
    """A field of :class:`SimConfig` out of range: ``field``, ``value``, ``problem``."""

    def __init__(self, field: str, value: object, problem: str) -> None:
        super().__init__(f"{field} {value!r}: {problem}")
        self.field = field
        self.value = value
        self.problem = problem


class SimConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    world: str = "default"
    """A shipped world's name (``corridor``) or the path of a world file."""
    system: str = "rap"
    """System name on the fabric: topics are ``rap/<system>/data/...``."""
    name: str = "sim_world"
    """The simulator's node name on the fabric (its liveliness token, admin verbs, trace
    and log keys): a system model's component that runs it gives its own name."""
    lockstep: bool = False
    """Step as fast as the host allows (deterministic); else real time x ``speed``."""
    speed: float = 1.0
    """Real-time factor without ``lockstep``: sim seconds per wall second."""
    duration: float | None = None
    """Seconds of sim time to simulate; None: until stopped."""
    rerun: str | None = None
    """Write a Rerun recording to this ``.rrd`` file."""
    sync_timeout: float = 2.0
    """In lockstep with a loop: seconds to wait for the cycle of a scan to end."""

    def __post_init__(self) -> None:
        if not self.world:
            raise SimConfigError("world", self.world, "give a shipped world's name or a path")
        try:
            keys.system_pattern(self.system)
        except keys.KeyError_ as exc:
            raise SimConfigError("system", self.system, str(exc)) from None
        try:
            keys.alive(self.system, self.name)
        except keys.KeyError_ as exc:
            raise SimConfigError("name", self.name, str(exc)) from None
        if not (math.isfinite(self.speed) and 0 < self.speed <= MAX_REALTIME_FACTOR):
            raise SimConfigError(
                "speed",
                self.speed,
                f"the real-time factor must be a number > 0 and at most {MAX_REALTIME_FACTOR:g}",
            )
        if self.duration is not None and not (
            math.isfinite(self.duration) and 0 < self.duration <= MAX_DURATION
        ):
            raise SimConfigError(
                "duration",
                self.duration,
                f"give seconds of sim time > 0 and at most {MAX_DURATION:g}, or none to run "
                "until stopped",
            )
        if self.rerun is not None and not self.rerun:
            raise SimConfigError("rerun", self.rerun, "give the path of an .rrd file, or none")
        if not (math.isfinite(self.sync_timeout) and self.sync_timeout > 0):
            raise SimConfigError("sync_timeout", self.sync_timeout, "give seconds > 0")

    @property
    def realtime_factor(self) -> float | None:
        """None in lockstep, else ``speed``."""
        return None if self.lockstep else self.speed
