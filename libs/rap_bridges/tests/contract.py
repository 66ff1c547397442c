"""The contract every bridge passes, and the harness that runs it against each protocol.

Each protocol has an :class:`Outside`: the server or peer at the other end of a bridge,
run by the test itself so that it can be stopped and started again on the same port.

- MQTT: a mosquitto of the test's own on a free loopback port, with persistence (the
  sessions of clients that asked for one, and the messages queued for them, outlive a
  restart, as on a production broker); an aiomqtt receiver with a session of its own
  collects what ``out`` bridges publish, and a sender publishes to ``in`` bridges.
- TCP: a peer server written with anyio and the documented frame format; it
  acknowledges numbered frames, records what it gets and sends frames to every
  connected bridge.

Every other protocol's outside lives in ``outside_<protocol>.py`` beside this file (a
class ``Outside`` with the members of :class:`Outside` below, and ``require_server()``).
The fabric side is a :class:`rap_sdk.MemoryFabric`; the tests are in
``test_contract.py``, parametrized over :data:`PROTOCOLS`.
"""

from __future__ import annotations

import importlib
import os
import subprocess
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, Protocol

import aiomqtt
import anyio
import msgspec
from anyio.abc import SocketStream, TaskGroup
from anyio.streams.buffered import BufferedByteReceiveStream
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from rap_bridges import Backoff, Bridge, BridgeSpec, Direction, Frame
from rap_bridges.spec import PROTOCOLS as KNOWN_PROTOCOLS
from rap_bridges.tcp import HEADER_ACK, HEADER_SENDER, HEADER_SEQ, encode_frame, read_frame
from rap_schemas import Envelope, Message, keys
from rap_sdk import InboxPolicy, MemoryFabric, Overflow, Sealer
from rap_sdk.fabric import Fabric, free_port
from rap_sdk.testing import accepting, require_binary, stop_process

PROTOCOLS = KNOWN_PROTOCOLS
"""Every protocol with a bridge: the contract runs against each."""
SYSTEM = "bridges"
KEY = keys.data(SYSTEM, "reading")
OUT_TOPIC = "contract/out"
IN_TOPIC = "contract/in"
TIMEOUT = 20.0


class Reading(Message, frozen=True):
    """The message of the contract's port."""

    TYPE = "test.Reading/1"

    n: int
    note: str = ""


def fast_backoff() -> Backoff:
    return Backoff(initial=0.05, max=0.5)


# -- the fabric side --------------------------------------------------------------------


class FabricSide:
    """The fabric of a test: publishes readings and records what arrives on KEY."""

    def __init__(self, fabric: Fabric) -> None:
        self.fabric = fabric
        self.sealer = Sealer("contract-test")
        self.got: list[Envelope] = []
        self._changed = anyio.Event()

    async def publish(
        self, n: int, *, cycle: bytes | None = None, cause: bytes | None = None
    ) -> None:
        await self.fabric.publish(
            KEY, self.sealer.seal_out(KEY, Reading(n=n), cycle=cycle, cause=cause)
        )

    async def record(self, *, task_status: Any = anyio.TASK_STATUS_IGNORED) -> None:
        policy = InboxPolicy(capacity=1_000_000, overflow=Overflow.FIFO, block=False)
        with self.fabric.subscribe(KEY, policy) as sub:
            task_status.started()
            async for sample in sub:
                self.got.append(msgspec.msgpack.decode(sample.payload, type=Envelope))
                self._changed.set()
                self._changed = anyio.Event()

    def readings(self) -> list[int]:
        return [msgspec.msgpack.decode(e.body, type=Reading).n for e in self.got]

    async def wait_for(self, n: int, timeout: float = TIMEOUT) -> None:
        with anyio.fail_after(timeout):
            while len(self.got) < n:
                await self._changed.wait()


@asynccontextmanager
async def fabric_side(tg: TaskGroup) -> AsyncIterator[FabricSide]:
    async with MemoryFabric() as fabric:
        side = FabricSide(fabric)
        await tg.start(side.record)
        yield side


# -- the outside ----------------------------------------------------------------------


class Outside(Protocol):
    protocol: str
    received: list[Frame]
    """What ``out`` bridges delivered, in order."""

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec: ...
    async def start(self) -> None: ...
    async def stop(self) -> None: ...
    async def send(self, frames: list[Frame]) -> None:
        """Hand frames to the ``in`` bridge (as a client of the protocol would)."""

    async def wait_received(self, n: int, timeout: float = TIMEOUT) -> None: ...


class _Received:
    def __init__(self) -> None:
        self.received: list[Frame] = []
        self._changed = anyio.Event()

    def add(self, frame: Frame) -> None:
        self.received.append(frame)
        self._changed.set()
        self._changed = anyio.Event()

    async def wait_received(self, n: int, timeout: float = TIMEOUT) -> None:
        with anyio.fail_after(timeout):
            while len(self.received) < n:
                await self._changed.wait()


class MosquittoServer:
    """A mosquitto of the test's own on ``port``, with persistence in ``directory``;
    :meth:`stop` and :meth:`start` again restart it on the same port."""

    def __init__(
        self,
        directory: Path,
        port: int,
        *,
        passwords: dict[str, str] | None = None,
        tls: tuple[Path, Path, Path] | None = None,
    ) -> None:
        """``passwords``: user -> password, and no anonymous client; ``tls``: the CA,
        certificate and key of a TLS-only listener that asks clients for a certificate
        of that CA."""
        self.binary = require_binary("mosquitto", hint="apt-get install mosquitto")
        self.port = port
        self.conf = directory / "mosquitto.conf"
        lines = [
            f"listener {port} 127.0.0.1",
            "persistence true",
            f"persistence_location {directory}/",
            f"log_dest file {directory / 'mosquitto.log'}",
        ]
        if os.geteuid() == 0:
            lines.append("user root")  # it would become 'mosquitto' and lose the folder
        self.password_file: Path | None = None
        if passwords:
            self.passwd = require_binary("mosquitto_passwd", hint="apt-get install mosquitto")
            self.password_file = directory / "mosquitto.passwd"
            text = "".join(f"{user}:{pw}\n" for user, pw in passwords.items())
            self.password_file.write_text(text, encoding="utf-8")
            lines += ["allow_anonymous false", f"password_file {self.password_file}"]
        else:
            lines.append("allow_anonymous true")
        if tls is not None:
            ca, cert, key = tls
            lines += [f"cafile {ca}", f"certfile {cert}", f"keyfile {key}"]
            lines.append("require_certificate true")
        self.conf.write_text("\n".join(lines) + "\n", encoding="utf-8")
        self._proc: Any = None

    async def start(self) -> None:
        if self.password_file is not None and b"$" not in self.password_file.read_bytes():
            await anyio.run_process([self.passwd, "-U", str(self.password_file)])  # hash them
        self._proc = await anyio.open_process(
            [self.binary, "-c", str(self.conf)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        proc = self._proc
        await accepting(
            self.port, lambda: None if proc.returncode is None else "mosquitto exited at start"
        )

    async def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            await stop_process(proc, grace=10)
            await proc.aclose()


def _user_properties(props: Any) -> dict[str, str]:
    return {str(k): str(v) for k, v in getattr(props, "UserProperty", None) or ()}


class MqttOutside(_Received):
    protocol = "mqtt"

    def __init__(self, directory: Path, tg: TaskGroup) -> None:
        super().__init__()
        self.server = MosquittoServer(directory, free_port())
        self.port = self.server.port
        self._tg = tg
        self.ready = anyio.Event()
        """Set while the receiver is subscribed."""

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec:
        address = OUT_TOPIC if direction == "out" else IN_TOPIC
        kw.setdefault("format", "json")
        return BridgeSpec(
            protocol="mqtt", url=f"mqtt://127.0.0.1:{self.port}", address=address, **kw
        )

    def client(self, identifier: str, *, persistent: bool) -> aiomqtt.Client:
        props = Properties(PacketTypes.CONNECT)
        props.SessionExpiryInterval = 600 if persistent else 0
        return aiomqtt.Client(
            "127.0.0.1",
            self.port,
            identifier=identifier,
            protocol=aiomqtt.ProtocolVersion.V5,
            clean_start=not persistent,
            properties=props,
            timeout=5,
        )

    async def start(self) -> None:
        await self.server.start()

    async def stop(self) -> None:
        await self.server.stop()

    async def receive_forever(self) -> None:
        """The receiver of ``out`` bridges: a persistent session, reconnected after a
        restart (messages published meanwhile are queued for it by the broker)."""
        while True:
            try:
                async with self.client("contract-receiver", persistent=True) as c:
                    await c.subscribe(OUT_TOPIC, qos=1)
                    self.ready.set()
                    async for m in c.messages:
                        payload = m.payload if isinstance(m.payload, bytes) else b""
                        self.add(Frame(payload, _user_properties(m.properties)))
            except aiomqtt.MqttError:
                if self.ready.is_set():
                    self.ready = anyio.Event()
                await anyio.sleep(0.05)

    async def start_receiver(self) -> None:
        self._tg.start_soon(self.receive_forever)
        with anyio.fail_after(10):
            await self.ready.wait()

    async def send(self, frames: list[Frame]) -> None:
        async with self.client("contract-sender", persistent=False) as c:
            for f in frames:
                props = Properties(PacketTypes.PUBLISH)
                if f.headers:
                    props.UserProperty = list(f.headers.items())
                await c.publish(IN_TOPIC, f.payload, qos=1, properties=props)


class TcpOutside(_Received):
    """A TCP peer server of the test's own (anyio and the documented frame format)."""

    protocol = "tcp"

    def __init__(self, directory: Path, tg: TaskGroup) -> None:
        super().__init__()
        self.port = free_port()
        self._tg = tg
        self._scope: anyio.CancelScope | None = None
        self.conns: list[SocketStream] = []
        self._joined = anyio.Event()
        self.seen: dict[str, int] = {}

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec:
        kw.setdefault("format", "json")
        return BridgeSpec(protocol="tcp", url=f"tcp://127.0.0.1:{self.port}", **kw)

    async def start(self) -> None:
        listener = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=self.port)
        scope = self._scope = anyio.CancelScope()

        async def serve() -> None:
            with scope:
                async with listener:
                    await listener.serve(self._conn)

        self._tg.start_soon(serve)

    async def stop(self) -> None:
        if self._scope is not None:
            self._scope.cancel()
            self._scope = None
        for c in self.conns:
            await c.aclose()
        self.conns.clear()
        self._joined = anyio.Event()
        await anyio.sleep(0.05)  # the cancelled server lets go of its port

    async def _conn(self, stream: SocketStream) -> None:
        self.conns.append(stream)
        self._joined.set()
        reader = BufferedByteReceiveStream(stream)
        async with stream:
            try:
                while True:
                    headers, payload = await read_frame(reader, 1 << 22)
                    seq = headers.pop(HEADER_SEQ, None)
                    sender = headers.pop(HEADER_SENDER, "")
                    if seq is not None:
                        if int(seq) > self.seen.get(sender, -1):
                            self.seen[sender] = int(seq)
                            self.add(Frame(payload, headers))
                        await stream.send(encode_frame(b"", {HEADER_ACK: seq}))
                    elif HEADER_ACK not in headers:
                        self.add(Frame(payload, headers))
            except (anyio.EndOfStream, anyio.IncompleteRead, anyio.BrokenResourceError):
                pass
            except anyio.ClosedResourceError:
                pass
            finally:
                if stream in self.conns:
                    self.conns.remove(stream)

    async def start_receiver(self) -> None:
        """Nothing to start: the peer records what every connection brings."""

    async def send(self, frames: list[Frame]) -> None:
        with anyio.fail_after(TIMEOUT):
            while not self.conns:
                await self._joined.wait()
        data = b"".join(encode_frame(f.payload, dict(f.headers)) for f in frames)
        await self.conns[-1].send(data)


def _module(protocol: str) -> Any:
    """The harness module of a protocol other than MQTT and TCP:
    ``outside_<protocol>.py`` beside this file, with ``Outside`` (the class) and
    ``require_server()``."""
    return importlib.import_module(f"libs.rap_bridges.tests.outside_{protocol.replace('-', '_')}")


def require_server(protocol: str) -> None:
    """Skip, or fail with ``RAP_REQUIRE_SERVICES=1``, when the server a protocol's
    outside needs is not installed (call it before any task group: a skip raised inside
    one reaches pytest wrapped in an exception group)."""
    if protocol == "mqtt":
        require_binary("mosquitto", hint="apt-get install mosquitto")
    elif protocol != "tcp":
        _module(protocol).require_server()


OutsideFactory = Callable[[Path, TaskGroup], Any]
OUTSIDES: dict[str, OutsideFactory] = {"mqtt": MqttOutside, "tcp": TcpOutside}


def outside_factory(protocol: str) -> OutsideFactory:
    if protocol not in OUTSIDES:
        OUTSIDES[protocol] = _module(protocol).Outside
    return OUTSIDES[protocol]


@asynccontextmanager
async def outside_of(protocol: str, directory: Path, tg: TaskGroup) -> AsyncIterator[Any]:
    out = outside_factory(protocol)(directory, tg)
    try:
        yield out
    finally:
        with anyio.CancelScope(shield=True):
            await out.stop()


def bridge(
    outside: Any, fabric: Fabric, direction: Direction, *, name: str = "contract", **kw: Any
) -> Bridge:
    return Bridge(
        name,
        outside.spec(direction, **kw),
        fabric,
        KEY,
        direction=direction,
        message=Reading,
        backoff=fast_backoff(),
    )


def json_frame(n: int, **headers: str) -> Frame:
    return Frame(msgspec.json.encode(Reading(n=n)), headers)


def numbers(frames: list[Frame]) -> list[int]:
    return [msgspec.json.decode(f.payload, type=Reading).n for f in frames]


async def until(cond: Callable[[], bool], timeout: float = 10.0) -> None:
    """Wait until ``cond()`` holds (polled: counters have no event of their own)."""
    with anyio.fail_after(timeout):
        for _ in range(int(timeout / 0.01) + 1):
            if cond():
                return
            await anyio.sleep(0.01)
    raise TimeoutError(f"{cond} did not hold within {timeout} s")
