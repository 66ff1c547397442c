"""The AMQP contract's outside: a RabbitMQ node of the test process's own, and clients
written with aio-pika's own API (not the bridge's link) at the other end of the bridges.

The node is the installed ``rabbitmq-server``, started once per test process (a node
takes seconds to boot) with a name, ports, data, logs and Erlang cookie of its own, so
that it never touches the machine's broker and two test processes never meet: it runs
until the process exits. :meth:`RabbitNode.stop_app` and :meth:`RabbitNode.start_app`
restart the broker in it (``rabbitmqctl stop_app`` / ``start_app``, about 0.5 s and
1.5 s): every listener and connection is closed, durable queues and their persistent
messages are kept, as across a production broker's restart. Each :class:`Outside` uses
queues of its own, so the tests sharing the node never see each other's messages.

The node also listens for TLS (a CA, broker and client certificates of its own in
``RabbitNode.certs``; clients must show a certificate of that CA).
"""

from __future__ import annotations

import atexit
import json
import os
import secrets
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import aio_pika
import anyio
from aio_pika.abc import AbstractIncomingMessage
from anyio.abc import TaskGroup
from rap_bridges import BridgeSpec, Direction, Frame
from rap_sdk.fabric import free_port
from rap_sdk.testing import accepting, require_binary

from libs.rap_bridges.tests.contract import _Received
from libs.rap_sdk.tests.certs_support import make_certs

HINT = "apt-get install rabbitmq-server"
BOOT_TIMEOUT = 60.0
CTL_TIMEOUT = 30.0


def require_server() -> None:
    require_binary("rabbitmq-server", hint=HINT)
    require_binary("rabbitmqctl", hint=HINT)


def _scripts() -> tuple[str, str]:
    """``rabbitmq-server`` and ``rabbitmqctl`` to run as this user. Distribution packages
    (Debian's) install a wrapper in sbin that switches to the ``rabbitmq`` user and its
    home (its cookie, its data): the real scripts lie beside that wrapper."""
    ctl = require_binary("rabbitmqctl", hint=HINT)
    beside = Path(os.path.realpath(ctl)).parent
    server, real_ctl = beside / "rabbitmq-server", beside / "rabbitmqctl"
    if server.exists() and real_ctl.exists():
        return str(server), str(real_ctl)
    return require_binary("rabbitmq-server", hint=HINT), ctl


class RabbitNode:
    """A RabbitMQ node of this test process: ``rap-<pid>-<random>@localhost``, AMQP on
    ``port`` and AMQPS on ``tls_port`` (loopback), everything else in a temporary
    folder removed when it stops."""

    def __init__(self) -> None:
        self.server, self.ctl_path = _scripts()
        self.name = f"rap-{os.getpid()}-{secrets.token_hex(3)}@localhost"
        self.port = free_port()
        self.tls_port = free_port()
        self.dist_port = free_port()
        self.folder: Path | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self.app_running = False
        atexit.register(self.shutdown)

    @property
    def certs(self) -> Path:
        """``ca.pem``, ``broker.pem``/``.key`` and ``client.pem``/``.key``."""
        assert self.folder is not None, "the node has not booted"
        return self.folder / "certs"

    def env(self) -> dict[str, str]:
        assert self.folder is not None
        d = self.folder
        return {
            **os.environ,
            "HOME": str(d),  # the Erlang cookie of the node and of its rabbitmqctl
            "LC_ALL": "C.UTF-8",
            "RABBITMQ_NODENAME": self.name,
            "RABBITMQ_NODE_IP_ADDRESS": "127.0.0.1",
            "RABBITMQ_NODE_PORT": str(self.port),
            "RABBITMQ_DIST_PORT": str(self.dist_port),
            "ERL_EPMD_ADDRESS": "127.0.0.1",
            "RABBITMQ_SERVER_ADDITIONAL_ERL_ARGS": "-kernel inet_dist_use_interface {127,0,0,1}",
            "RABBITMQ_CONF_ENV_FILE": str(d / "rabbitmq-env.conf"),
            "RABBITMQ_CONFIG_FILE": str(d / "rabbitmq.conf"),
            "RABBITMQ_ADVANCED_CONFIG_FILE": str(d / "advanced.config"),
            "RABBITMQ_MNESIA_BASE": str(d / "mnesia"),
            "RABBITMQ_LOG_BASE": str(d / "log"),
            "RABBITMQ_PID_FILE": str(d / "node.pid"),
            "RABBITMQ_ENABLED_PLUGINS_FILE": str(d / "enabled_plugins"),
            "RABBITMQ_PLUGINS_EXPAND_DIR": str(d / "plugins-expand"),
        }

    def _prepare(self) -> Path:
        d = Path(tempfile.mkdtemp(prefix="rap-rabbitmq-"))
        certs = make_certs(
            d / "certs",
            {"broker": "", "client": ""},
            system="amqp",
            hosts={"broker": ["127.0.0.1", "localhost"]},
        )
        (d / "rabbitmq-env.conf").write_text("", encoding="utf-8")  # not the machine's
        (d / "enabled_plugins").write_text("[].\n", encoding="utf-8")  # none: boots faster
        conf = [
            f"listeners.tcp.1 = 127.0.0.1:{self.port}",
            f"listeners.ssl.1 = 127.0.0.1:{self.tls_port}",
            f"ssl_options.cacertfile = {certs / 'ca.pem'}",
            f"ssl_options.certfile = {certs / 'broker.pem'}",
            f"ssl_options.keyfile = {certs / 'broker.key'}",
            "ssl_options.verify = verify_peer",
            "ssl_options.fail_if_no_peer_cert = true",
            "disk_free_limit.absolute = 1MB",  # a shared machine's disk must not block it
            "log.console = false",
            "log.file.level = info",
        ]
        (d / "rabbitmq.conf").write_text("\n".join(conf) + "\n", encoding="utf-8")
        return d

    def _spawn(self) -> subprocess.Popen[bytes]:
        assert self.folder is not None
        with (self.folder / "server.out").open("wb") as out:
            return subprocess.Popen(
                [self.server],
                env=self.env(),
                cwd=self.folder,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
            )

    async def boot(self) -> None:
        self.folder = await anyio.to_thread.run_sync(self._prepare)
        self._proc = await anyio.to_thread.run_sync(self._spawn)
        with anyio.fail_after(BOOT_TIMEOUT):
            for port in (self.port, self.tls_port):
                await self._wait_listening(port)
        self.app_running = True

    async def _wait_listening(self, port: int) -> None:
        def exited() -> str | None:
            if self._proc is None or self._proc.poll() is not None:
                return f"rabbitmq-server exited at start: {self.log_tail()}"
            return None

        await accepting(port, exited, timeout=None)  # boot() sets the deadline

    def log_tail(self, lines: int = 20) -> str:
        if self.folder is None:
            return ""
        texts = [p.read_text(errors="replace") for p in self.folder.glob("log/*.log")]
        texts.append((self.folder / "server.out").read_text(errors="replace"))
        return "\n".join("\n".join(t.splitlines()[-lines:]) for t in texts if t)

    async def ctl(self, *args: str) -> str:
        """``rabbitmqctl -n <node> args``: its output; RuntimeError when it fails."""
        with anyio.fail_after(CTL_TIMEOUT):
            done = await anyio.run_process(
                [self.ctl_path, "-n", self.name, *args], env=self.env(), check=False
            )
        if done.returncode != 0:
            raise RuntimeError(
                f"rabbitmqctl {' '.join(args)}: exit {done.returncode}: "
                f"{done.stderr.decode(errors='replace')}{done.stdout.decode(errors='replace')}"
            )
        return done.stdout.decode()

    async def list_queues(self) -> dict[str, dict[str, Any]]:
        """name -> {durable, messages, consumers, type}, as rabbitmqctl sees them."""
        text = await self.ctl(
            "list_queues", "-q", "--formatter", "json", "name", "durable", "messages",
            "consumers", "type",
        )  # fmt: skip
        return {q["name"]: q for q in json.loads(text)}

    async def start(self) -> None:
        """Boot the node, or start its broker again after :meth:`stop_app`."""
        if self._proc is None or self._proc.poll() is not None:
            await anyio.to_thread.run_sync(self.shutdown)  # what is left of a dead node
            await self.boot()
        elif not self.app_running:
            await self.ctl("start_app")
            self.app_running = True

    async def stop_app(self) -> None:
        if self._proc is not None and self.app_running:
            self.app_running = False
            await self.ctl("stop_app")

    def shutdown(self) -> None:
        """Stop the node and remove its folder (at the process's exit)."""
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.terminate()  # the script stops the node and its Erlang VM
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)
            self.folder = None
        self.app_running = False


_NODE: RabbitNode | None = None


def node() -> RabbitNode:
    """This test process's RabbitMQ node (booted by its first ``start``)."""
    global _NODE
    if _NODE is None:
        _NODE = RabbitNode()
    return _NODE


def amqp_headers(message: AbstractIncomingMessage) -> dict[str, str]:
    return {str(k): str(v) for k, v in (message.headers or {}).items()}


class Outside(_Received):
    """The broker (this process's node) and aio-pika clients: one receiving what ``out``
    bridges publish to their queue, one publishing to the queue of ``in`` bridges."""

    protocol = "amqp"

    def __init__(self, directory: Path, tg: TaskGroup) -> None:
        super().__init__()
        self.node = node()
        token = secrets.token_hex(4)
        self.out_queue = f"contract.out.{token}"
        self.in_queue = f"contract.in.{token}"
        self._tg = tg
        self.ready = anyio.Event()
        """Set while the receiver consumes."""

    @property
    def url(self) -> str:
        return f"amqp://127.0.0.1:{self.node.port}"

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec:
        kw.setdefault("format", "json")
        address = self.out_queue if direction == "out" else self.in_queue
        return BridgeSpec(protocol="amqp", url=self.url, address=address, **kw)

    async def connect(self) -> aio_pika.abc.AbstractConnection:
        return await aio_pika.connect(host="127.0.0.1", port=self.node.port, timeout=5)

    async def start(self) -> None:
        await self.node.start()

    async def stop(self) -> None:
        await self.node.stop_app()

    async def receive_forever(self) -> None:
        """The receiver of ``out`` bridges: consumes their durable queue with manual
        acknowledgements, connecting again after a restart (the queue and what it holds
        outlive it)."""
        while True:
            try:
                connection = await self.connect()
            except (aio_pika.exceptions.AMQPError, OSError):
                await anyio.sleep(0.05)
                continue
            try:
                channel = await connection.channel()
                await channel.set_qos(prefetch_count=100)
                queue = await channel.declare_queue(self.out_queue, durable=True)

                async def on_message(message: AbstractIncomingMessage) -> None:
                    self.add(Frame(message.body, amqp_headers(message)))
                    await message.ack()

                lost = anyio.Event()
                connection.close_callbacks.add(lambda *_, lost=lost: lost.set())
                await queue.consume(on_message)
                self.ready.set()
                await lost.wait()
            except (aio_pika.exceptions.AMQPError, OSError):
                pass
            finally:
                if self.ready.is_set():
                    self.ready = anyio.Event()
                with anyio.CancelScope(shield=True):
                    await connection.close()
            await anyio.sleep(0.05)

    async def start_receiver(self) -> None:
        self._tg.start_soon(self.receive_forever)
        with anyio.fail_after(10):
            await self.ready.wait()

    async def send(self, frames: list[Frame]) -> None:
        """Publish to the ``in`` bridges' queue (declared durable, as the bridge does),
        persistent and confirmed by the broker."""
        connection = await self.connect()
        try:
            channel = await connection.channel(publisher_confirms=True)
            await channel.declare_queue(self.in_queue, durable=True)
            for f in frames:
                message = aio_pika.Message(
                    f.payload,
                    headers=dict(f.headers),
                    delivery_mode=aio_pika.DeliveryMode.PERSISTENT,
                )
                await channel.default_exchange.publish(message, self.in_queue)
        finally:
            with anyio.CancelScope(shield=True):
                await connection.close()
