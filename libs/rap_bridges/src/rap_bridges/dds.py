"""The DDS link: a port as a ROS 2 topic, over Eclipse Cyclone DDS (docs/bridges/dds.md).

- Naming: ``url: dds://<domain>`` is the DDS domain (ROS 2's ``ROS_DOMAIN_ID``);
  ``address: /scan`` is the ROS 2 topic, the DDS topic ``rt/scan``.
- Format ``cdr``: the ROS 2 message the port's RAP type maps to
  (:data:`rap_bridges.ros2.MAPPINGS`: ``rap.LaserScan/2`` is ``sensor_msgs/msg/LaserScan``
  and so on), converted by the documented rules; a message with a value the other side
  cannot hold is rejected with the reason and counted, and the next one is taken. A ROS
  message has no place for the envelope's cycle and cause: they are not carried.
  Formats ``envelope``, ``json`` and ``raw`` travel in ``rap_msgs/msg/Frame`` (headers
  and payload bytes), which carries cycle, cause, type and sender in its headers.
- QoS 0: best effort, volatile. QoS >= 1: reliable and transient-local, with a history
  of the last ``buffer`` messages (KEEP_LAST, also for late joiners), so that a reader
  that joins late or comes back gets what was written meanwhile. ``out``: a message
  counts as sent once it is in the writer's history, which DDS delivers reliably to every
  matched reader and replays to readers that join later (a reader that comes back may
  get again what it had: at least once); a writer whose readers do not acknowledge fast
  enough blocks (DDS flow control) for up to :data:`BLOCK_S`, then the link counts as
  lost and the message is written again. QoS 2 also waits, after each message, until
  every matched reader acknowledged it (slower: a DDS heartbeat round per message).
  ``in``: the reader asks for the same QoS, so at QoS >= 1 it matches only writers that
  offer reliable, transient-local data; an incompatible peer is reported, with the fix.
- The connection: DDS has no server. :meth:`DdsLink.open` makes the participant, topic
  and reader or writer once (they are kept across reconnects, and so are the writer's
  history and the reader's cache) and returns when a peer has matched: a reader of the
  topic (``out``) or a writer (``in``). The link is up while one is there: when the last
  one leaves, the link is down (:class:`LinkDown`) and the bridge buffers. A peer that
  leaves cleanly is seen at once, one that died when its lease ends (Cyclone's default:
  10 s). Local errors (a participant that cannot be made: bad configuration, no usable
  network interface) are :class:`LinkDown` with the fix.
- Cyclone's calls are synchronous: every one runs in a worker thread (the link's own
  limiter), never on the event loop; waits are sliced (:data:`SLICE_S`) so that a
  cancelled bridge stops promptly. Incoming samples are taken one at a time, so a sample
  that does not decode costs only itself.

The configuration is Cyclone's: ``CYCLONEDDS_URI`` (network interfaces, peers, multicast),
as for ROS 2's ``rmw_cyclonedds_cpp``.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Final

import anyio
import msgspec
from cyclonedds.core import (
    DDSException,
    DDSStatus,
    InstanceState,
    ReadCondition,
    SampleState,
    ViewState,
    WaitSet,
)
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from rap_schemas import Message

from .core import HEADER_TYPE, Deliver, Frame, FrameRefused, LinkContext, LinkDown
from .ros2 import Frame_, FrameHeader_, RosMapping, Unrepresentable, dds_topic, mapping_for
from .spec import BridgeSpec

__all__ = ["BLOCK_S", "MAX_HEADERS", "SLICE_S", "DdsLink", "endpoint_qos"]

log = logging.getLogger(__name__)

SLICE_S: Final = 0.2
"""The longest a worker thread waits in one go (a cancelled bridge stops within it)."""
BLOCK_S: Final = 5.0
"""How long a reliable write may wait for room (readers that do not acknowledge)."""
ACK_S: Final = 10.0
"""QoS 2: how long a message may wait for every reader's acknowledgement."""
CLOSE_ACK_S: Final = 2.0
"""On closing (QoS >= 1): how long the last messages may wait for acknowledgements."""
PEER_WARN_S: Final = 10.0
"""After this long without a peer, the link logs that it is still waiting (once)."""
BATCH: Final = 256
"""Samples taken from the reader per worker-thread call."""
MAX_HEADERS: Final = 64
"""The most headers an incoming generic frame may carry..."""
MAX_HEADER_BYTES: Final = 64 * 1024
"""...and their total size (keys and values, UTF-8)."""

_INCOMPATIBLE: Final[dict[int, str]] = {
    2: "durability",
    3: "presentation",
    4: "deadline",
    5: "latency budget",
    6: "ownership",
    8: "liveliness",
    10: "partition",
    11: "reliability",
    12: "destination order",
    25: "data representation",
}
"""DDS QoS policy ids (Cyclone's) that can keep two endpoints from matching, by name."""
SERIALIZE_ERRORS: Final = (struct.error, UnicodeError, ValueError, TypeError, OverflowError)
"""What serializing a sample raises for a value its IDL type cannot hold."""


def endpoint_qos(spec: BridgeSpec, *, writer: bool) -> Qos:
    """The QoS of a bridge's reader or writer (see the module's documentation). The
    writer writes CDR as ROS 2 does (XCDR1); the reader takes XCDR1 and XCDR2."""
    rep = Policy.DataRepresentation(
        use_cdrv0_representation=True, use_xcdrv2_representation=not writer
    )
    history = Policy.History.KeepLast(spec.buffer)
    if spec.qos == 0:
        return Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, history, rep)
    return Qos(
        Policy.Reliability.Reliable(max_blocking_time=duration(seconds=BLOCK_S)),
        Policy.Durability.TransientLocal,
        history,
        Policy.DurabilityService(
            cleanup_delay=0,
            history=Policy.History.KeepLast(spec.buffer),
            max_samples=-1,
            max_instances=-1,
            max_samples_per_instance=-1,
        ),
        rep,
    )


@dataclass(slots=True)
class _Entities:
    participant: DomainParticipant
    topic: Topic[Any]
    writer: DataWriter[Any] | None
    reader: DataReader[Any] | None
    waitset: WaitSet

    def delete(self) -> None:
        # deleting the participant deletes its topic, endpoints, conditions and waitset
        self.participant.__del__()


@dataclass(slots=True)
class _Batch:
    frames: list[Frame] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)
    """Why samples were refused (reported by the event loop's side)."""
    matched: int = 0


@dataclass(frozen=True, slots=True)
class _Peers:
    matched: int
    incompatible: str | None
    """The policy that kept a peer from matching since the last look, if one did."""


class DdsLink:
    """One port on one ROS 2 topic (see the module's documentation)."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        self.spec = spec
        self.ctx = ctx
        self.topic = dds_topic(spec.address)
        self.mapping: RosMapping | None = mapping_for(ctx.message) if spec.format == "cdr" else None
        self.type: type[IdlStruct] = self.mapping.ros if self.mapping else Frame_
        self.message: type[Message] | None = ctx.message
        self._encode_rap: Callable[[Any], bytes] = msgspec.msgpack.Encoder().encode
        self._ents: _Entities | None = None
        self._limiter = anyio.CapacityLimiter(2)  # the link's own threads: run and send
        self._warned = False
        self._mismatch = False
        """A peer's QoS could not match at the last attempt."""

    @property
    def where(self) -> str:
        return f"{self.spec.where} (DDS topic {self.topic}, {self.type.__idl_typename__})"

    @property
    def _out(self) -> bool:
        return self.ctx.direction == "out"

    async def _thread(self, fn: Callable[..., Any], *args: Any) -> Any:
        return await anyio.to_thread.run_sync(fn, *args, limiter=self._limiter)

    # -- the connection -------------------------------------------------------------------

    async def open(self) -> None:
        if self._mismatch and self._ents is not None and not (self._out and self.spec.qos):
            # made again, so that a peer that is still there is judged (and reported) anew;
            # a writer at qos >= 1 is kept for its history
            ents, self._ents = self._ents, None
            await self._thread(ents.delete)
        self._mismatch = False
        if self._ents is None:
            self._ents = await self._thread(self._create)
        ents = self._ents
        began = anyio.current_time()
        while True:
            peers: _Peers = await self._thread(self._wait_peers, ents, True)
            if peers.matched:
                return
            if peers.incompatible is not None:
                self._mismatch = True
                raise LinkDown(*self._incompatible(peers.incompatible))
            if not self._warned and anyio.current_time() - began >= PEER_WARN_S:
                self._warned = True
                log.warning(
                    "bridge %s: no ROS 2 node %s %s on DDS domain %d yet (%.0f s); waiting - "
                    "check ROS_DOMAIN_ID and that both sides share a network interface "
                    "(CYCLONEDDS_URI)",
                    self.ctx.name,
                    "subscribes to" if self._out else "publishes",
                    self.spec.address,
                    self.spec.domain,
                    PEER_WARN_S,
                )

    def _create(self) -> _Entities:
        domain = self.spec.domain
        try:
            participant = DomainParticipant(domain)
        except DDSException as exc:
            raise LinkDown(
                f"cannot join DDS domain {domain}: {exc}",
                "check the Cyclone DDS configuration (CYCLONEDDS_URI: its XML and network "
                "interfaces)",
            ) from None
        try:
            topic: Topic[Any] = Topic(participant, self.topic, self.type)
            waitset = WaitSet(participant)
            writer: DataWriter[Any] | None = None
            reader: DataReader[Any] | None = None
            if self._out:
                writer = DataWriter(participant, topic, endpoint_qos(self.spec, writer=True))
                writer.set_status_mask(
                    DDSStatus.PublicationMatched | DDSStatus.OfferedIncompatibleQos
                )
                waitset.attach(writer)
            else:
                reader = DataReader(participant, topic, endpoint_qos(self.spec, writer=False))
                reader.set_status_mask(
                    DDSStatus.SubscriptionMatched | DDSStatus.RequestedIncompatibleQos
                )
                waitset.attach(reader)
                mask = SampleState.Any | ViewState.Any | InstanceState.Any
                waitset.attach(ReadCondition(reader, mask))
        except DDSException as exc:
            participant.__del__()
            raise LinkDown(
                f"cannot make the {'writer' if self._out else 'reader'} of {self.topic}: {exc}",
                "another type under the same topic name in this process? one topic, one type",
            ) from None
        return _Entities(participant, topic, writer, reader, waitset)

    @staticmethod
    def _peers(ents: _Entities) -> _Peers:
        """Matched peers, and a peer with an incompatible QoS since the last look (reading
        the statuses resets the waitset's trigger)."""
        if ents.writer is not None:
            matched = ents.writer.get_publication_matched_status().current_count  # type: ignore[no-untyped-call]
            bad: Any = ents.writer.get_offered_incompatible_qos_status()  # type: ignore[no-untyped-call]
        else:
            assert ents.reader is not None
            matched = ents.reader.get_subscription_matched_status().current_count  # type: ignore[no-untyped-call]
            bad = ents.reader.get_requested_incompatible_qos_status()  # type: ignore[no-untyped-call]
        policy = None
        if bad.total_count_change:
            policy = _INCOMPATIBLE.get(bad.last_policy_id, f"QoS policy {bad.last_policy_id}")
        return _Peers(int(matched), policy)

    def _wait_peers(self, ents: _Entities, for_match: bool) -> _Peers:
        """Wait (one slice at most) until peers match (``for_match``) or are gone."""
        try:
            peers = self._peers(ents)
            if (peers.matched > 0) is for_match or peers.incompatible:
                return peers
            ents.waitset.wait(duration(seconds=SLICE_S))
            return self._peers(ents)
        except DDSException as exc:
            raise self._lost(ents, exc) from None

    def _incompatible(self, policy: str) -> tuple[str, str]:
        mine = "reliable, transient-local" if self.spec.qos else "best effort, volatile"
        if self._out:
            return (
                f"a reader of {self.spec.address} asks for a {policy} this writer does not "
                f"offer ({mine}, depth {self.spec.buffer})",
                "have the subscriber ask for what the bridge offers, or change the bridge's "
                "qos (1: reliable, transient-local; 0: best effort, volatile)",
            )
        return (
            f"a writer of {self.spec.address} does not offer the {policy} this reader asks "
            f"for ({mine})",
            "at qos 1 publish with reliability reliable and durability transient_local "
            "(ros2 topic pub --qos-reliability reliable --qos-durability transient_local), "
            "or give the bridge qos: 0 (best effort, takes any publisher)",
        )

    def _lost(self, ents: _Entities, exc: DDSException) -> LinkDown:
        """A DDS call failed: the entities are dropped (made again at the next open)."""
        if self._ents is ents:
            self._ents = None
            ents.delete()
        return LinkDown(f"DDS error on {self.topic}: {exc}", "see the Cyclone DDS log")

    async def run(self, deliver: Deliver) -> None:
        ents = self._ents
        if ents is None:
            raise LinkDown("not open")
        if self._out:  # nothing comes in: watch the readers
            while True:
                peers: _Peers = await self._thread(self._wait_peers, ents, False)
                if peers.incompatible:
                    log.warning(
                        "bridge %s: %s - %s", self.ctx.name, *self._incompatible(peers.incompatible)
                    )
                if not peers.matched:
                    raise LinkDown(
                        f"no reader of {self.spec.address} is left",
                        f"start the ROS 2 node that subscribes to {self.spec.address}",
                    )
        while True:
            batch: _Batch = await self._thread(self._take, ents)
            for reason in batch.rejected:
                self.ctx.reject(reason)
            for frame in batch.frames:
                await deliver(frame)
            if not batch.frames and not batch.rejected and not batch.matched:
                raise LinkDown(
                    f"no writer of {self.spec.address} is left",
                    f"start the ROS 2 node that publishes {self.spec.address}",
                )

    # -- in ---------------------------------------------------------------------------------

    def _take(self, ents: _Entities) -> _Batch:
        """Up to :data:`BATCH` frames (waiting one slice at most when there are none), the
        reasons of the samples refused, and how many writers match."""
        reader = ents.reader
        assert reader is not None
        batch = _Batch()
        try:
            for attempt in range(2):
                while len(batch.frames) + len(batch.rejected) < BATCH:
                    try:
                        got = reader.take(1)
                    except DDSException:
                        raise
                    except Exception as exc:  # a sample that does not decode, whatever it holds
                        batch.rejected.append(
                            f"a sample on {self.topic} that is no {self.type.__idl_typename__}: "
                            f"{type(exc).__name__}: {exc}"
                        )
                        continue
                    if not got:
                        break
                    sample = got[0]
                    if sample.sample_info.valid_data:  # else: a writer left, no message
                        self._frame(sample, batch)
                peers = self._peers(ents)
                batch.matched = peers.matched
                if peers.incompatible:
                    log.warning(
                        "bridge %s: %s - %s", self.ctx.name, *self._incompatible(peers.incompatible)
                    )
                if batch.frames or batch.rejected or attempt or not peers.matched:
                    break
                ents.waitset.wait(duration(seconds=SLICE_S))
        except DDSException as exc:
            raise self._lost(ents, exc) from None
        return batch

    def _frame(self, sample: Any, batch: _Batch) -> None:
        """The frame of one sample, or the reason it is refused, into ``batch``."""
        if self.mapping is None:
            headers = {h.key: h.value for h in sample.headers}
            size = sum(len(k) + len(v) for k, v in headers.items())
            if len(sample.headers) > MAX_HEADERS or size > MAX_HEADER_BYTES:
                batch.rejected.append(
                    f"a frame with {len(sample.headers)} headers of {size} bytes (the limit: "
                    f"{MAX_HEADERS} headers, {MAX_HEADER_BYTES} bytes)"
                )
                return
            batch.frames.append(Frame(bytes(sample.payload), headers))
            return
        assert self.message is not None
        try:
            body = self.mapping.from_ros(sample)
        except Unrepresentable as exc:
            batch.rejected.append(
                f"{self.mapping.ros_name} does not map to {self.message.TYPE}: {exc.reason}"
            )
            return
        try:
            payload = self._encode_rap(body)
        except (ValueError, OverflowError, TypeError) as exc:  # e.g. a stamp past int64
            batch.rejected.append(
                f"{self.mapping.ros_name} does not map to {self.message.TYPE}: {exc}"
            )
            return
        batch.frames.append(Frame(payload, {HEADER_TYPE: self.message.TYPE}))

    # -- out --------------------------------------------------------------------------------

    async def send(self, frame: Frame) -> None:
        ents = self._ents
        if ents is None:
            raise LinkDown("not open")
        refused: str | None = await self._thread(self._write, ents, frame)
        if refused is not None:
            raise FrameRefused(refused)

    def _sample(self, frame: Frame) -> IdlStruct | str:
        """The sample of a frame, or the reason it cannot be one."""
        if self.mapping is None:
            headers = [FrameHeader_(k, v) for k, v in frame.headers.items()]
            return Frame_(headers=headers, payload=frame.payload)
        assert self.message is not None
        try:
            message = msgspec.msgpack.decode(frame.payload, type=self.message)
            return self.mapping.to_ros(message)
        except Unrepresentable as exc:
            return f"{self.message.TYPE} does not map to {self.mapping.ros_name}: {exc.reason}"
        except (msgspec.DecodeError, ValueError) as exc:  # not what the bridge's codec makes
            return f"not a {self.message.TYPE} msgpack body: {exc}"

    def _write(self, ents: _Entities, frame: Frame) -> str | None:
        """Write one frame; the reason when it cannot be written (it is not sent)."""
        writer = ents.writer
        assert writer is not None
        sample = self._sample(frame)
        if isinstance(sample, str):
            return sample
        try:
            writer.write(sample)
        except DDSException as exc:
            if exc.code == DDSException.DDS_RETCODE_TIMEOUT:
                raise LinkDown(
                    f"the readers of {self.spec.address} did not take what was written for "
                    f"{BLOCK_S:g} s",
                    "a reader is stuck or far too slow: check the subscribing node",
                ) from None
            raise self._lost(ents, exc) from None
        except SERIALIZE_ERRORS as exc:
            return f"cannot write it as {self.type.__idl_typename__}: {exc}"
        try:
            confirmed = self.spec.qos < 2 or writer.wait_for_acks(duration(seconds=ACK_S))
        except DDSException as exc:
            raise self._lost(ents, exc) from None
        if not confirmed:
            raise LinkDown(
                f"the readers of {self.spec.address} did not acknowledge within {ACK_S:g} s",
                "a reader is stuck or unreachable: check the subscribing node and the network",
            )
        return None

    async def close(self) -> None:
        ents, self._ents = self._ents, None
        if ents is None:
            return
        with anyio.CancelScope(shield=True):
            await self._thread(self._finish, ents)

    def _finish(self, ents: _Entities) -> None:
        if ents.writer is not None and self.spec.qos:
            try:  # the last messages reach the readers before the writer goes
                ents.writer.wait_for_acks(duration(seconds=CLOSE_ACK_S))
            except DDSException as exc:
                log.debug("bridge %s: waiting for acknowledgements: %s", self.ctx.name, exc)
        ents.delete()
