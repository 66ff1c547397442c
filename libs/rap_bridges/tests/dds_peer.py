"""A plain Cyclone DDS participant: the ROS 2 side of the bridge contract, in a process of
its own (run by ``outside_dds.Outside``; ``python dds_peer.py --help``).

Its types are its own, from the documented ``rap_msgs`` definitions (not the bridge's
code). It writes ``rap_msgs/msg/Frame`` on ``--write`` and, with ``--receive`` or once told,
reads them on ``--read``, both reliable and transient-local with a deep history, as a
ROS 2 node asking for "latched" data would. It talks JSON lines:

- stdin: ``{"op": "receive"}`` (make the reader now), ``{"op": "send", "frames":
  [{"payload": "<hex>", "headers": {...}}]}``; end of input: leave (after the readers
  acknowledged what was written), deleting the participant, so that the other side sees
  it go at once.
- stdout: ``{"ev": "ready"}``, ``{"ev": "receiving"}``, ``{"ev": "sent", "n": N}``,
  ``{"ev": "frame", "payload": "<hex>", "headers": {...}, "ts": <source timestamp, ns>}``.
"""

import argparse
import json
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any

from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import sequence, uint8
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

DEPTH = 20_000


@dataclass
class FrameHeader_(IdlStruct, typename="rap_msgs::msg::dds_::FrameHeader_"):
    key: str
    value: str


@dataclass
class Frame_(IdlStruct, typename="rap_msgs::msg::dds_::Frame_"):
    headers: Annotated[Sequence[FrameHeader_], sequence(FrameHeader_)]
    payload: Annotated[Sequence[int], sequence(uint8)]


def latched(depth: int) -> Qos:
    return Qos(
        Policy.Reliability.Reliable(max_blocking_time=duration(seconds=5)),
        Policy.Durability.TransientLocal,
        Policy.History.KeepLast(depth),
        Policy.DurabilityService(
            cleanup_delay=0,
            history=Policy.History.KeepLast(depth),
            max_samples=-1,
            max_instances=-1,
            max_samples_per_instance=-1,
        ),
    )


class Peer:
    def __init__(self, domain: int, read: str, write: str) -> None:
        self.participant = DomainParticipant(domain)
        self.read_topic: Topic[Frame_] = Topic(self.participant, read, Frame_)
        self.writer = DataWriter(
            self.participant, Topic(self.participant, write, Frame_), latched(DEPTH)
        )
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def emit(self, event: dict[str, Any]) -> None:
        with self._lock:
            sys.stdout.write(json.dumps(event) + "\n")
            sys.stdout.flush()

    def receive(self) -> None:
        if self._thread is None:
            reader = DataReader(self.participant, self.read_topic, latched(DEPTH))
            self._thread = threading.Thread(target=self._take, args=(reader,), daemon=True)
            self._thread.start()

    def _take(self, reader: DataReader[Frame_]) -> None:
        waitset = WaitSet(self.participant)
        waitset.attach(ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any))
        while not self._stop.is_set():
            waitset.wait(duration(seconds=0.1))
            for s in reader.take(1000):
                if s.sample_info.valid_data:
                    headers = {h.key: h.value for h in s.headers}
                    ts = s.sample_info.source_timestamp
                    self.emit(
                        {
                            "ev": "frame",
                            "payload": bytes(s.payload).hex(),
                            "headers": headers,
                            "ts": ts,
                        }
                    )

    def send(self, frames: list[dict[str, Any]]) -> None:
        for f in frames:
            headers = [FrameHeader_(k, v) for k, v in f["headers"].items()]
            self.writer.write(Frame_(headers=headers, payload=bytes.fromhex(f["payload"])))
        self.emit({"ev": "sent", "n": len(frames)})

    def leave(self) -> None:
        self.writer.wait_for_acks(duration(seconds=5))
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.participant.__del__()  # announces the leave to the other participants


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--domain", type=int, required=True)
    ap.add_argument("--read", required=True, help="the DDS topic to read (rt/...)")
    ap.add_argument("--write", required=True, help="the DDS topic to write (rt/...)")
    ap.add_argument("--receive", action="store_true", help="read from the start")
    args = ap.parse_args()
    peer = Peer(args.domain, args.read, args.write)
    if args.receive:
        peer.receive()
    peer.emit({"ev": "ready"})
    for line in sys.stdin:
        command = json.loads(line)
        if command["op"] == "receive":
            peer.receive()
            peer.emit({"ev": "receiving"})
        elif command["op"] == "send":
            peer.send(command["frames"])
    peer.leave()


if __name__ == "__main__":
    main()
