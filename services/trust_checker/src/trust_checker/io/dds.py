"""The checker's inputs from ROS 2 topics over DDS (Cyclone DDS), beside its other
transports (docs/trust_checker.md).

Inputs: each input stream of the running spec is read from the ROS 2 topic
``DdsConfig.topics`` maps it to (``{"latency": {"topic": "/robot/latency", "type":
"std_msgs/msg/Float64"}}``), else from ``/<stream>`` (DDS topic ``rt/<stream>``) as
``rap_msgs/msg/Frame``. A ``rap_msgs/msg/Frame``'s payload is read as on MQTT (any of
the forms of :mod:`trust_checker.io.codec`, refused by the same rules); a
``std_msgs/msg/Bool``, ``Int64``, ``Float64`` or ``String`` gives its ``data`` (a
non-finite Float64 is refused). Several streams may read one topic (of one type); each
sample is one message, one arrival. The readers follow the running spec's inputs across
hot swaps. QoS ``0`` reads best effort (every publisher matches, sensor data as well);
``1`` reads reliable, transient-local data (only publishers that offer it, and their
history when the checker joins).

Outputs and verdicts do not go out on DDS: they go to the other transports and sinks
(MQTT, Redis, the fabric, the console). Hot swap is not offered over DDS (no way to tell
who sent an update).

Bad input (a payload the codec refuses, a sample that does not decode) is rejected:
counted by reason in ``stats.rejections``, logged rate-limited, and the next sample is
taken. Cyclone's calls are synchronous: they all run in one worker thread of the
transport's own, which waits on the readers 0.2 s at a time (so the checker stops
promptly) and hands the samples over in batches. The network is Cyclone's configuration
(``CYCLONEDDS_URI``), as for ROS 2's ``rmw_cyclonedds_cpp``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import anyio
from anyio.abc import TaskStatus
from cyclonedds.core import (
    DDSException,
    InstanceState,
    ReadCondition,
    SampleState,
    ViewState,
    WaitSet,
)
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from rap_bridges.ros2 import Bool_, Float64_, Frame_, Int64_, String_, dds_topic
from rap_schemas import TrustSpecStatus
from rap_sdk.errors import ConfigError
from rap_sdk.rejections import Rejections

from ..config import DdsConfig
from .codec import CodecError, decode_payload
from .ports import OutputLike
from .session import Session
from .ticks import Arrival

__all__ = ["TYPES", "DdsTransport", "DdsTransportStats"]

log = logging.getLogger(__name__)

TYPES: Final[dict[str, type[IdlStruct]]] = {
    "rap_msgs/msg/Frame": Frame_,
    "std_msgs/msg/Bool": Bool_,
    "std_msgs/msg/Int64": Int64_,
    "std_msgs/msg/Float64": Float64_,
    "std_msgs/msg/String": String_,
}
"""The ROS 2 message types an input is read as, by ROS 2's name."""
SLICE_S: Final = 0.2
BATCH: Final = 256


@dataclass(slots=True)
class DdsTransportStats:
    rejections: Rejections
    """Samples refused (a payload the codec cannot read, one that does not decode),
    counted by reason."""
    taken: int = 0
    """Samples taken from the readers (before any check)."""
    readers: int = 0
    """Readers open now (one per topic the running spec reads)."""


@dataclass(slots=True)
class _Reader:
    reader: DataReader[Any]
    condition: ReadCondition
    topic: str
    streams: list[str]


@dataclass(slots=True)
class _Taken:
    arrivals: list[tuple[list[str], Any, str]] = field(default_factory=list)
    """(streams, value, ROS 2 topic)."""
    rejected: list[tuple[str, str]] = field(default_factory=list)
    """(ROS 2 topic, reason)."""


class DdsTransport:
    """Feeds ``session`` from ROS 2 topics (it adds itself to the session's sinks, to
    follow hot swaps). Run :meth:`run` in a task group, next to ``session.run``."""

    def __init__(self, session: Session, config: DdsConfig) -> None:
        self.session = session
        self.config = config
        self.stats = DdsTransportStats(Rejections(f"{session.node} (dds)", log))
        self._limiter = anyio.CapacityLimiter(1)
        self._participant: DomainParticipant | None = None
        self._waitset: WaitSet | None = None
        self._readers: dict[tuple[str, str], _Reader] = {}
        self._resync = True
        for stream in session.runner.inputs:
            config.topic_of(stream)  # ConfigError now for an input with no topic
        session.sinks.append(self)

    def _qos(self) -> Qos:
        history = Policy.History.KeepLast(self.config.depth)
        if self.config.qos == 0:
            return Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, history)
        return Qos(
            Policy.Reliability.Reliable(max_blocking_time=duration(seconds=1)),
            Policy.Durability.TransientLocal,
            history,
        )

    # -- the worker thread ------------------------------------------------------------

    def _open(self) -> None:
        try:
            participant = DomainParticipant(self.config.domain)
        except DDSException as exc:
            raise ConfigError(
                f"DDS: cannot join domain {self.config.domain}: {exc} - check the Cyclone DDS "
                "configuration (CYCLONEDDS_URI: its XML and network interfaces)"
            ) from None
        self._participant = participant
        self._waitset = WaitSet(participant)

    def _sync(self) -> None:
        """Readers for the running spec's inputs, one per (topic, type); those no input
        needs any more are deleted."""
        participant, waitset = self._participant, self._waitset
        assert participant is not None
        assert waitset is not None
        want: dict[tuple[str, str], list[str]] = {}
        for stream in self.session.runner.inputs:
            try:
                where = self.config.topic_of(stream)
            except ConfigError as exc:  # a swapped-in spec's input: said, and not read
                log.error("dds: %s", exc)
                continue
            want.setdefault((where.topic, where.type), []).append(stream)
        for key in [k for k in self._readers if k not in want]:
            gone = self._readers.pop(key)
            waitset.detach(gone.condition)
            gone.reader.__del__()  # deletes its condition too
        types: dict[str, str] = {}
        for key, streams in want.items():
            if key in self._readers:
                self._readers[key].streams = streams
                types[key[0]] = key[1]
                continue
            topic, type_name = key
            if types.setdefault(topic, type_name) != type_name:  # DDS: one type per topic
                log.error(
                    "dds: inputs %s read %s as %s, but another input reads it as %s: one "
                    "type per topic - these inputs are not read",
                    ", ".join(streams),
                    topic,
                    type_name,
                    types[topic],
                )
                continue
            try:
                reader = DataReader(
                    participant,
                    Topic(participant, dds_topic(topic), TYPES[type_name]),
                    self._qos(),
                )
            except DDSException as exc:  # e.g. the topic exists with another type
                log.error(
                    "dds: cannot read %s as %s (%s): inputs %s are not read",
                    topic,
                    type_name,
                    exc,
                    ", ".join(streams),
                )
                continue
            mask = SampleState.Any | ViewState.Any | InstanceState.Any
            condition = ReadCondition(reader, mask)
            waitset.attach(condition)
            self._readers[key] = _Reader(reader, condition, topic, streams)
        self.stats.readers = len(self._readers)
        log.debug("dds: reading %s", {k[0]: r.streams for k, r in self._readers.items()})

    def _take(self) -> _Taken:
        """What the readers have (waiting one slice at most when they have nothing)."""
        if self._resync:
            self._resync = False
            self._sync()
        waitset = self._waitset
        assert waitset is not None
        taken = _Taken()
        for attempt in range(2):
            for r in list(self._readers.values()):
                while len(taken.arrivals) + len(taken.rejected) < BATCH:
                    try:
                        got = r.reader.take(1)
                    except DDSException:
                        raise
                    except Exception as exc:  # a sample that does not decode
                        taken.rejected.append((r.topic, f"{type(exc).__name__}: {exc}"))
                        continue
                    if not got:
                        break
                    sample = got[0]
                    if not sample.sample_info.valid_data:
                        continue  # a writer left: no message
                    try:
                        taken.arrivals.append((r.streams, _value(sample), r.topic))
                    except CodecError as exc:
                        taken.rejected.append((r.topic, exc.reason))
            if taken.arrivals or taken.rejected or attempt:
                break
            waitset.wait(duration(seconds=SLICE_S))
        return taken

    def _close(self) -> None:
        participant, self._participant = self._participant, None
        self._readers.clear()
        self._waitset = None
        if participant is not None:
            participant.__del__()  # its readers, conditions and waitset with it

    # -- the event loop's side ---------------------------------------------------------

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Join the domain, read the inputs until cancelled.
        ``task_status.started()`` once the readers are there."""
        thread = anyio.to_thread.run_sync
        try:
            await thread(self._open, limiter=self._limiter)
            self._resync = True
            taken = await thread(self._take, limiter=self._limiter)
            log.info(
                "dds: reading %d topic(s) on domain %d", self.stats.readers, self.config.domain
            )
            task_status.started()
            while True:
                self.stats.taken += len(taken.arrivals) + len(taken.rejected)
                for topic, reason in taken.rejected:
                    self.stats.rejections.reject(topic, reason)
                now = self.session.clock.time_ns
                await self.session.submit_many(
                    [Arrival(dict.fromkeys(s, v), now(), topic) for s, v, topic in taken.arrivals]
                )
                taken = await thread(self._take, limiter=self._limiter)
        finally:
            with anyio.CancelScope(shield=True):
                await thread(self._close, limiter=self._limiter)

    # -- the sink: only to follow the spec ---------------------------------------------

    async def outputs(self, outs: Sequence[OutputLike]) -> None:
        """Outputs do not go out on DDS (see the module's documentation)."""

    async def status(self, status: TrustSpecStatus) -> None:
        if status.ok:
            self._resync = True  # the worker makes the new spec's readers before its next wait


def _value(sample: Any) -> Any:
    """The stream value of a sample; :class:`CodecError` saying why not."""
    if isinstance(sample, Frame_):
        return decode_payload(bytes(sample.payload))
    data = sample.data  # a bool, an int64, a float or a str: a value as it is
    if type(data) is float and not math.isfinite(data):
        raise CodecError(f"std_msgs/msg/Float64 {data}: not a finite number - send a finite one")
    return data
