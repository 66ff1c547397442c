"""The contract's NATS outside: a ``nats-server -js`` of the test's own on a free loopback
port with its JetStream store in the test's folder; :meth:`NatsServer.stop` and
:meth:`NatsServer.start` restart it on the same port and store, so streams, consumers
and their positions outlive the restart as on a production server.

The client on the outside is nats-py used directly (not the bridge's link):

- the receiver of ``out`` bridges owns a stream of its own on the ``out`` subject and
  reads it with a pull consumer that starts after the last stream sequence it has
  seen, made again after every restart (so it misses nothing and takes nothing twice);
- the sender publishes to ``in`` bridges with JetStream (each publication acknowledged
  by the server), the headers as NATS headers.
"""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import anyio
import nats
import nats.errors
import nats.js.errors
from anyio.abc import TaskGroup
from nats.aio.client import Client
from nats.js.api import AckPolicy, ConsumerConfig, DeliverPolicy, StorageType
from rap_bridges import BridgeSpec, Direction, Frame
from rap_sdk.fabric import free_port
from rap_sdk.testing import accepting, require_binary, stop_process

from libs.rap_bridges.tests.contract import _Received

OUT_SUBJECT = "contract.out"
IN_SUBJECT = "contract.in"
RECEIVER_STREAM = "CONTRACT_OUT"


def require_server() -> None:
    require_binary("nats-server", hint="apt-get install nats-server")


async def quiet(exc: Exception) -> None:
    """nats-py's error callback: the tests see errors where they are raised."""


class NatsServer:
    """A nats-server of the test's own with JetStream, its store in ``directory``."""

    def __init__(
        self,
        directory: Path,
        port: int,
        *,
        user: tuple[str, str] | None = None,
        tls: tuple[Path, Path, Path] | None = None,
    ) -> None:
        """``user``: the only (name, password) admitted; ``tls``: the CA, certificate and
        key of a TLS-only server that asks clients for a certificate of that CA."""
        self.binary = require_binary("nats-server", hint="apt-get install nats-server")
        self.port = port
        self.directory = directory
        store = directory / "jetstream"
        store.mkdir(parents=True, exist_ok=True)
        self.args = [
            self.binary,
            "-js",
            "-sd",
            str(store),
            "-a",
            "127.0.0.1",
            "-p",
            str(port),
            "-l",
            str(directory / "nats-server.log"),
        ]
        if user is not None:
            self.args += ["--user", user[0], "--pass", user[1]]
        if tls is not None:
            ca, cert, key = tls
            self.args += ["--tlsverify", "--tlscacert", str(ca)]
            self.args += ["--tlscert", str(cert), "--tlskey", str(key)]
        self._proc: Any = None

    @property
    def url(self) -> str:
        return f"nats://127.0.0.1:{self.port}"

    async def start(self) -> None:
        self._proc = await anyio.open_process(
            self.args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        proc, log = self._proc, f"{self.directory}/nats-server.log"
        await accepting(
            self.port,
            lambda: None if proc.returncode is None else f"nats-server exited at start; see {log}",
        )

    async def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            await stop_process(proc, grace=10)
            await proc.aclose()

    async def client(self, **kw: Any) -> Client:
        """A nats-py connection that does not reconnect by itself."""
        return await nats.connect(
            self.url, allow_reconnect=False, max_reconnect_attempts=0, error_cb=quiet, **kw
        )


def _frame(data: bytes, headers: dict[str, str] | None) -> Frame:
    return Frame(data, {k: v for k, v in (headers or {}).items() if not k.startswith("Nats-")})


class Outside(_Received):
    protocol = "nats"

    def __init__(self, directory: Path, tg: TaskGroup) -> None:
        super().__init__()
        self.server = NatsServer(directory, free_port())
        self.port = self.server.port
        self._tg = tg
        self.ready = anyio.Event()
        """Set while the receiver is reading."""
        self.last = 0
        """The receiver's last stream sequence."""

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec:
        address = OUT_SUBJECT if direction == "out" else IN_SUBJECT
        kw.setdefault("format", "json")
        return BridgeSpec(
            protocol="nats", url=f"nats://127.0.0.1:{self.port}", address=address, **kw
        )

    async def start(self) -> None:
        await self.server.start()

    async def stop(self) -> None:
        await self.server.stop()

    async def receive_forever(self) -> None:
        while True:
            try:
                nc = await self.server.client()
            except (OSError, nats.errors.Error):
                await anyio.sleep(0.05)  # the server is down: try again
                continue
            try:
                js = nc.jetstream()
                await js.add_stream(
                    name=RECEIVER_STREAM, subjects=[OUT_SUBJECT], storage=StorageType.FILE
                )
                config = ConsumerConfig(
                    deliver_policy=DeliverPolicy.BY_START_SEQUENCE,
                    opt_start_seq=self.last + 1,
                    ack_policy=AckPolicy.NONE,
                    inactive_threshold=60.0,
                )
                pull = await js.pull_subscribe(OUT_SUBJECT, stream=RECEIVER_STREAM, config=config)
                self.ready.set()
                while True:
                    try:
                        msgs = await pull.fetch(500, timeout=1.0)
                    except nats.errors.TimeoutError:
                        continue
                    for m in msgs:
                        seq = m.metadata.sequence.stream
                        if seq > self.last:
                            self.last = seq
                            self.add(_frame(m.data, m.headers))
            except (OSError, nats.errors.Error):
                if self.ready.is_set():
                    self.ready = anyio.Event()
            finally:
                with anyio.CancelScope(shield=True):
                    await nc.close()

    async def start_receiver(self) -> None:
        self._tg.start_soon(self.receive_forever)
        with anyio.fail_after(10):
            await self.ready.wait()

    async def send(self, frames: list[Frame]) -> None:
        nc = await self.server.client()
        try:
            js = nc.jetstream()
            for f in frames:
                await js.publish(IN_SUBJECT, f.payload, headers=dict(f.headers) or None)
        finally:
            await nc.close()
