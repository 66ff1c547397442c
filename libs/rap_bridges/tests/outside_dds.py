"""The contract's DDS outside: the ROS 2 side, a plain Cyclone DDS participant
(``dds_peer.py``) in a child process of the test's own, on the loopback interface only.

DDS has no server: :meth:`Outside.stop` is the peer participant leaving (its process
deletes the participant, so the bridge sees it go at once, then exits) and
:meth:`Outside.start` a new peer process joining the same domain and topics: for the
bridge, a ROS 2 node restarting. The domain is this test process's own (:data:`DOMAIN`)
and the topics carry the process id, so parallel test runs never meet; the
configuration (:data:`LOOPBACK`, in ``CYCLONEDDS_URI``, which the peer inherits) keeps
every participant on ``lo`` with unicast discovery, no multicast.

The peer reads and writes ``rap_msgs/msg/Frame`` reliably with transient-local
durability, as the bridge at QoS 1 does: a restarted peer gets the bridge writer's
history again (at least once). Like a subscriber that remembers the newest message it
has processed, the outside keeps the newest source timestamp it took and passes over
older samples (:attr:`Outside.replayed` counts them); a message the bridge wrote twice has
a new timestamp and is kept, so the contract still sees every real duplicate.
"""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Final

import anyio
from anyio.abc import Process, TaskGroup
from anyio.streams.buffered import BufferedByteReceiveStream
from rap_bridges import BridgeSpec, Direction, Frame
from rap_bridges.ros2 import dds_topic
from rap_sdk.testing import require_binary, stop_process

from libs.rap_bridges.tests.contract import TIMEOUT, _Received

PEER: Final = Path(__file__).with_name("dds_peer.py")
DOMAIN: Final = 100 + os.getpid() % 130
"""This test process's DDS domain (100-229: never ROS 2's default 0)."""
LOOPBACK: Final = (
    '<CycloneDDS><Domain Id="any">'
    '<General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
    "<AllowMulticast>false</AllowMulticast></General>"
    "<Discovery><ParticipantIndex>auto</ParticipantIndex>"
    "<MaxAutoParticipantIndex>30</MaxAutoParticipantIndex>"
    '<Peers><Peer address="127.0.0.1"/></Peers>'
    "<SPDPInterval>1 s</SPDPInterval></Discovery>"
    "</Domain></CycloneDDS>"
)
"""Cyclone DDS on the loopback interface only, discovering by unicast to 127.0.0.1 (and
announcing itself every second, so that a lost announcement costs a second, not 30)."""
_TOPICS = itertools.count()


def loopback_only() -> None:
    """Make this process's (and its children's) DDS participants loopback-only."""
    os.environ["CYCLONEDDS_URI"] = LOOPBACK


def require_server() -> None:
    """The DDS "server" is the cyclonedds package itself (a dependency of rap-bridges);
    its command-line tool is the sign that it is installed whole."""
    require_binary("cyclonedds", hint="it comes with the cyclonedds Python package: uv sync")


class Outside(_Received):
    protocol = "dds"

    def __init__(self, directory: Path, tg: TaskGroup) -> None:
        super().__init__()
        loopback_only()
        self._tg = tg
        base = f"/contract_{os.getpid()}_{next(_TOPICS)}"
        self.out_topic = f"{base}/out"
        """The ROS 2 topic ``out`` bridges write (the peer reads it)."""
        self.in_topic = f"{base}/in"
        """The ROS 2 topic ``in`` bridges read (the peer writes it)."""
        self.receiving = False
        self.newest = 0
        """The newest source timestamp taken (ns)."""
        self.replayed = 0
        """Samples passed over: older than one taken already (a transient-local replay)."""
        self._proc: Process | None = None
        self._scope: anyio.CancelScope | None = None
        self._replies: list[dict[str, Any]] = []
        self._replied = anyio.Event()

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec:
        kw.setdefault("format", "json")
        address = self.out_topic if direction == "out" else self.in_topic
        return BridgeSpec(protocol="dds", url=f"dds://{DOMAIN}", address=address, **kw)

    async def start(self) -> None:
        args = [sys.executable, str(PEER), "--domain", str(DOMAIN)]
        args += ["--read", dds_topic(self.out_topic), "--write", dds_topic(self.in_topic)]
        if self.receiving:
            args.append("--receive")
        self._replies.clear()
        proc = self._proc = await anyio.open_process(
            args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=None
        )
        scope = self._scope = anyio.CancelScope()

        async def pump() -> None:
            with scope:
                assert proc.stdout is not None
                lines = BufferedByteReceiveStream(proc.stdout)
                while True:
                    try:
                        line = await lines.receive_until(b"\n", 1 << 26)
                    except (anyio.EndOfStream, anyio.IncompleteRead, anyio.ClosedResourceError):
                        return
                    self._event(json.loads(line))

        self._tg.start_soon(pump)
        await self._expect("ready")

    def _event(self, event: dict[str, Any]) -> None:
        if event["ev"] != "frame":
            self._replies.append(event)
            self._replied.set()
            self._replied = anyio.Event()
            return
        if event["ts"] <= self.newest:
            self.replayed += 1
            return
        self.newest = event["ts"]
        self.add(Frame(bytes.fromhex(event["payload"]), event["headers"]))

    async def _expect(self, what: str) -> dict[str, Any]:
        with anyio.fail_after(TIMEOUT):
            while not self._replies:
                await self._replied.wait()
        event = self._replies.pop(0)
        assert event["ev"] == what, event
        return event

    async def _command(self, command: dict[str, Any], reply: str) -> None:
        proc = self._proc
        assert proc is not None, "the peer is not running"
        assert proc.stdin is not None
        await proc.stdin.send(json.dumps(command).encode() + b"\n")
        await self._expect(reply)

    async def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        with anyio.CancelScope(shield=True):
            assert proc.stdin is not None
            await proc.stdin.aclose()  # the peer leaves: acknowledged writes, then goodbye
            with anyio.move_on_after(10):
                await proc.wait()
            await stop_process(proc, grace=5)  # only if it did not leave by itself
            if self._scope is not None:
                self._scope.cancel()
            await proc.aclose()

    async def start_receiver(self) -> None:
        self.receiving = True
        if self._proc is not None:
            await self._command({"op": "receive"}, "receiving")

    async def send(self, frames: list[Frame]) -> None:
        batch = [{"payload": f.payload.hex(), "headers": dict(f.headers)} for f in frames]
        await self._command({"op": "send", "frames": batch}, "sent")
