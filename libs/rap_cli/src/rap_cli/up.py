"""``rap up``, ``rap down``, ``rap health``: run a model's compute nodes on this machine.

    rap up model.yaml --node robot      # robot's router, knowledge, runner, ... supervised
    rap up model.yaml --all             # every compute node, their routers linked
    rap health model.yaml --node robot  # exit 0 when every Node of robot is alive
    rap down model.yaml                 # stop what rap up runs

Each compute node runs one Zenoh router (:mod:`rap_cli.router`); its other processes are
Zenoh clients of it (``RAP_ZENOH_CONFIG``), see :mod:`rap_cli.deploy`. A node's files live
in ``<run-dir>/<node>/`` (the run dir defaults to ``<model folder>/.rap/<system>``):
``zenoh-router.json5`` and ``zenoh-client.json5`` (written by ``rap up``), ``logs/<name>.log``
(each process's output), ``logs/<name>.jsonl`` (the JSON lines log of each RAP service:
knowledge, runner, trust checkers; ``rap logs`` reads them), ``data/`` (knowledge's SQLite
file) and ``up.json``, the state of the ``rap up`` that runs the node (its pid, each
process's pid, state, restarts and metrics address: each RAP service serves Prometheus
metrics on a free loopback port), which ``rap down`` and ``rap health`` read.

``rap up`` supervises: a process that exits is restarted after a delay that doubles from
0.5 s to 30 s (back to 0.5 s once it stayed up 30 s). SIGTERM or SIGINT stops every
process in reverse start order (SIGTERM, then SIGKILL after a grace period).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Annotated, Any

import anyio
import typer
from anyio.abc import Process, TaskGroup
from rap_schemas import DeploymentPlan, PlanDocument, PlanError, keys, load_plan

from .cli import FAILED, OK, USAGE, failed, usage
from .deploy import (
    CONFIG_ENV,
    Paths,
    ProcessSpec,
    TlsFiles,
    client_config,
    knowledge_node,
    node_processes,
    render_zenoh,
    router_config,
    router_id,
)
from .reach import AsOpt, CertsOpt

__all__ = [
    "STATE_FILE",
    "NodeRun",
    "expected_nodes",
    "plan_run",
    "read_state",
    "register",
    "router_id",
]

STATE_FILE = "up.json"
BACKOFF_FIRST = 0.5
BACKOFF_MAX = 30.0
BACKOFF_RESET = 30.0
"""Seconds a process must stay up for its restart delay to start again at BACKOFF_FIRST."""
ROUTER_START = 30.0
"""Seconds a router has to start listening."""
OUTPUT_LINGER = 2.0
"""Seconds the output of an exited process is still read (a child of it may hold it)."""
MAX_LINE = 64 * 1024

ModelArg = Annotated[
    Path,
    typer.Argument(
        help="The system model (model.yaml, or the folder holding it).",
        show_default=False,
        metavar="MODEL",
    ),
]
RunDirOpt = Annotated[
    Path | None,
    typer.Option(
        "--run-dir",
        help="Where the nodes' configs, logs, data and state live "
        "(default: `<model folder>/.rap/<system>`).",
        show_default=False,
    ),
]


# -- errors ------------------------------------------------------------------------------


# -- the model and what to run -------------------------------------------------------------


def _load(model: Path) -> tuple[Path, PlanDocument]:
    file = model / "model.yaml" if model.is_dir() else model
    try:
        doc = load_plan(file)
    except PlanError as exc:
        usage(str(exc))
    return file.resolve(), doc


def _default_run_dir(model: Path, plan: DeploymentPlan) -> Path:
    return model.parent / ".rap" / plan.system


def _check_nodes(doc: PlanDocument, nodes: Iterable[str], option: str = "--node") -> list[str]:
    names = list(doc.plan.compute_nodes)
    out: list[str] = []
    for node in nodes:
        if node not in doc.plan.compute_nodes:
            usage(
                f"{doc.where(('compute_nodes',), key=True)}: {option} {node!r} is not a compute "
                f"node of the model - use one of: {', '.join(names)}"
            )
        if node not in out:
            out.append(node)
    return out


def _one_node(doc: PlanDocument, node: str | None) -> str:
    if node is not None:
        return _check_nodes(doc, [node])[0]
    names = list(doc.plan.compute_nodes)
    if len(names) == 1:
        return names[0]
    usage(
        f"{doc.source}: the model has {len(names)} compute nodes ({', '.join(names)}) - "
        "choose one with --node NAME"
    )


def _addresses(doc: PlanDocument, given: Sequence[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in given:
        node, sep, host = item.partition("=")
        if not sep or not node.strip() or not host.strip():
            usage(f"--address {item!r} is not NODE=HOST - write e.g. --address edge=10.0.0.2")
        out[_check_nodes(doc, [node.strip()], "--address")[0]] = host.strip()
    return out


def _log_level(text: str) -> str:
    if logging.getLevelNamesMapping().get(text.upper()) is None:
        usage(f"--log-level {text!r} is not a logging level - use DEBUG, INFO, WARNING or ERROR")
    return text.upper()


def expected_nodes(plan: DeploymentPlan, node: str) -> list[str]:
    """The Nodes of compute node ``node``'s share whose liveliness tokens say it is up:
    the components with a ``module:`` mapped there, and ``knowledge`` when it hosts it."""
    names = [n for n, c in plan.components_on(node).items() if c.module and not c.external]
    if knowledge_node(plan) == node:
        names.append("knowledge")
    return names


@dataclass
class NodeRun:
    """What ``rap up`` runs for one compute node."""

    node: str
    dir: Path
    paths: Paths
    local: str
    """The router's local endpoint, where the node's clients connect."""
    router: dict[str, Any]
    """The router's Zenoh config."""
    client: dict[str, Any]
    """The Zenoh config of the node's other processes."""
    processes: list[ProcessSpec]
    dashboard: str = ""
    """The adaptation manager's dashboard URL, on the node that hosts knowledge."""


def _free_ports(n: int) -> list[int]:
    """``n`` distinct free TCP ports on loopback."""
    with contextlib.ExitStack() as stack:
        ports = []
        for _ in range(n):
            sock = stack.enter_context(socket.socket(socket.AF_INET))
            sock.bind(("127.0.0.1", 0))
            ports.append(int(sock.getsockname()[1]))
        return ports


def _metrics_ports() -> Callable[[str], str]:
    """A free loopback ``HOST:PORT`` for each process's metrics, none given twice."""
    given: set[int] = set()

    def pick(name: str) -> str:
        while True:
            (port,) = _free_ports(1)
            if port not in given:
                given.add(port)
                return f"127.0.0.1:{port}"

    return pick


def plan_run(
    doc: PlanDocument,
    model: Path,
    nodes: Sequence[str],
    run_dir: Path,
    *,
    addresses: Mapping[str, str] | None = None,
    log_level: str = "INFO",
    link: bool = False,
    certs: Path | None = None,
) -> list[NodeRun]:
    """The configs and processes of ``nodes`` (nothing written, nothing started).

    Each router listens on a free loopback port for its node's clients, and on the node's
    ``listen`` endpoints (a compute node's name as host resolved as
    :func:`~rap_cli.deploy.resolve_endpoint` says). ``link``: the routers of ``nodes``
    also form one connected graph: the model's ``connect`` endpoints link some; every
    group still apart gets linked to the first node's local endpoint. ``certs``: the
    folder ``rap certs`` wrote, used when the model says ``fabric.tls`` (each router
    presents its node's certificate on its ``tls/`` links)."""
    plan = doc.plan
    addresses = dict(addresses or {})
    runs: list[NodeRun] = []
    metrics = _metrics_ports()
    for node, port in zip(nodes, _free_ports(len(nodes)), strict=True):
        secure = plan.fabric.tls and certs is not None
        paths = Paths.local(model, run_dir, node, certs if secure else None)
        # with TLS the node's own processes reach their router over it too, each with
        # its own certificate: that is what the router's access control goes by
        local = f"{'tls' if secure else 'tcp'}/127.0.0.1:{port}"
        tls = TlsFiles.of(certs, node) if secure and certs is not None else None
        conf = router_config(plan, node, local=[local], addresses=addresses, tls=tls)
        # one adaptation manager per system, beside knowledge; its dashboard on loopback
        http = metrics("manager") if knowledge_node(plan) == node else None
        procs = node_processes(
            doc,
            node,
            paths=paths,
            system=plan.system,
            log_level=log_level,
            addresses=addresses,
            metrics=metrics,
            log_dir=str(Path(paths.router_config).parent / "logs"),
            manager_http=http,
        )
        runs.append(
            NodeRun(
                node=node,
                dir=Path(paths.router_config).parent,
                paths=paths,
                local=local,
                router=conf,
                client=client_config(
                    local,
                    secure=secure,
                    max_sample_bytes=plan.fabric.max_sample_bytes,
                    shared_memory=plan.fabric.shared_memory,
                ),
                processes=procs,
                dashboard=f"http://{http}/" if http else "",
            )
        )
    if link and len(runs) > 1:
        _link(plan, runs)
    return runs


def _link(plan: DeploymentPlan, runs: list[NodeRun]) -> None:
    """Make the routers of ``runs`` one connected graph (see :func:`plan_run`)."""
    parent = {r.node: r.node for r in runs}

    def find(n: str) -> str:
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n

    for r in runs:
        for target in r.router["connect"]["endpoints"]:
            for other in runs:
                if other is not r and any(
                    _reaches(target, e) for e in other.router["listen"]["endpoints"]
                ):
                    parent[find(r.node)] = find(other.node)
    if plan.fabric.routers:  # every router connects to them: they meet there
        for r in runs[1:]:
            parent[find(r.node)] = find(runs[0].node)
    hub = runs[0]
    for r in runs[1:]:
        if find(r.node) != find(hub.node):
            r.router["connect"]["endpoints"].append(hub.local)
            parent[find(r.node)] = find(hub.node)


_WILDCARD = {"0.0.0.0", "[::]", "::"}
_LOOPBACK = {"127.0.0.1", "localhost", "[::1]", "::1"}


def _split(endpoint: str) -> tuple[str, str, str]:
    """(protocol, host, port) of ``tcp/host:port`` (empty parts when it has none)."""
    proto, _, rest = endpoint.partition("/")
    rest = rest.split("#", 1)[0].split("?", 1)[0]
    host, _, port = rest.rpartition(":")
    return proto, host, port


def _reaches(target: str, listen: str) -> bool:
    """Whether connecting to ``target`` on this machine reaches a listener on ``listen``."""
    p1, h1, port1 = _split(target)
    p2, h2, port2 = _split(listen)
    if p1 != p2 or not port1 or port1 != port2:
        return False
    return h1 == h2 or h2 in _WILDCARD or (h1 in _LOOPBACK and h2 in _LOOPBACK)


def _write_configs(runs: Sequence[NodeRun], system: str) -> None:
    for r in runs:
        for sub in (r.dir, r.dir / "logs", Path(r.paths.data_dir)):
            sub.mkdir(parents=True, exist_ok=True)
        Path(r.paths.router_config).write_text(
            render_zenoh(r.router, title=f"the Zenoh router of compute node {r.node} ({system})"),
            encoding="utf-8",
        )
        Path(r.paths.client_config).write_text(
            render_zenoh(
                r.client, title=f"the Zenoh clients of compute node {r.node}'s router ({system})"
            ),
            encoding="utf-8",
        )


# -- state files ---------------------------------------------------------------------------


def read_state(path: Path) -> dict[str, Any] | None:
    """A node's ``up.json``, or None when there is none."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except OSError as exc:
        usage(f"{path}: cannot read it ({exc.strerror}) - check its permissions")
    try:
        state = json.loads(text)
    except ValueError as exc:
        usage(f"{path}: not a rap up state file ({exc}) - delete it if no rap up runs")
    if not isinstance(state, dict):
        usage(f"{path}: not a rap up state file - delete it if no rap up runs")
    return state


def _identity(pid: int) -> str | None:
    """When process ``pid`` started (clock ticks since boot, from /proc), to tell it from
    a later process that got the same pid; "" where /proc does not say; None when there
    is no such process."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
            stat = f.read()
    except FileNotFoundError:
        return None
    except OSError:
        stat = ""
    fields = stat.rpartition(")")[2].split()
    if len(fields) > 19:
        return fields[19]
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        pass
    return ""


def _same_process(pid: Any, identity: Any) -> bool:
    """Whether ``pid`` still runs the process recorded with ``identity``."""
    if not isinstance(pid, int) or pid <= 0:
        return False
    now = _identity(pid)
    return now is not None and (not identity or not now or now == identity)


def _left_behind(state: dict[str, Any] | None) -> list[tuple[str, int]]:
    """The processes of a ``rap up`` that is gone but did not stop them (it was killed)."""
    if state is None or state.get("state") == "stopped" or _running(state):
        return []
    return [
        (str(c.get("name")), int(c["pid"]))
        for c in state.get("children") or []
        if isinstance(c, dict) and _same_process(c.get("pid"), c.get("identity"))
    ]


def _running(state: dict[str, Any] | None) -> bool:
    if state is None or state.get("state") == "stopped":
        return False
    sup = state.get("supervisor") or {}
    return _same_process(sup.get("pid"), sup.get("identity"))


# -- supervision -----------------------------------------------------------------------------


@dataclass(eq=False)
class Child:
    """One supervised process and its restarts."""

    node: str
    spec: ProcessSpec
    label: str
    argv: list[str]
    env: dict[str, str]
    cwd: Path
    log_path: Path
    log: IO[bytes] | None = None
    proc: Process | None = None
    state: str = "pending"
    restarts: int = 0
    last_exit: int | None = None
    identity: str | None = None
    stopping: bool = False
    tail: str = ""
    """Its last line of output."""
    ready: anyio.Event = field(default_factory=anyio.Event)
    """Set once a router says it listens."""
    spawned: anyio.Event = field(default_factory=anyio.Event)
    """Set once its first start has been tried."""
    done: anyio.Event = field(default_factory=anyio.Event)
    wake: anyio.Event = field(default_factory=anyio.Event)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def title(self) -> str:
        """Its name, with its node's when rap up runs several (``a/runner``)."""
        return self.label.strip()

    def stopped(self) -> bool:
        """Whether it is being stopped (a method: the flag changes across awaits)."""
        return self.stopping

    def alive(self) -> bool:
        return self.proc is not None and self.proc.returncode is None

    def signal(self, signum: signal.Signals) -> None:
        """Signal its process group (it leads one: ``start_new_session``)."""
        if self.proc is not None and self.proc.returncode is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, signum)


def _meaning(code: int) -> str:
    if code < 0:
        with contextlib.suppress(ValueError):
            return f" (killed by {signal.Signals(-code).name})"
    if code == USAGE:
        return " (its arguments or input are wrong: see its output above)"
    return ""


Output = tuple[IO[bytes] | None, bytes, str]


class Supervisor:
    """Starts, watches, restarts and stops the processes of some compute nodes."""

    def __init__(
        self,
        runs: Sequence[NodeRun],
        *,
        model: Path,
        system: str,
        grace: float,
        python: str = sys.executable,
    ) -> None:
        self.runs = list(runs)
        self.model = model
        self.system = system
        self.grace = grace
        self.state = "starting"
        self.started = time.time()
        self.identity: str | None = None
        labels = {
            (r.node, p.name): p.name if len(runs) == 1 else f"{r.node}/{p.name}"
            for r in runs
            for p in r.processes
        }
        width = max(len("rap"), *(len(v) for v in labels.values()))
        self._pad = width
        base = dict(os.environ)
        base.pop(CONFIG_ENV, None)  # the clients get their node's; the router needs none
        old = base.get("PYTHONPATH")
        base["PYTHONPATH"] = str(model.parent) + (os.pathsep + old if old else "")
        base["PYTHONUNBUFFERED"] = "1"
        self.children: list[Child] = [
            Child(
                node=r.node,
                spec=p,
                label=labels[(r.node, p.name)].ljust(width),
                argv=p.command(python),
                env={**base, **p.env},
                cwd=model.parent,
                log_path=r.dir / "logs" / f"{p.name}.log",
            )
            for r in runs
            for p in r.processes
        ]
        self.order: list[Child] = []
        """The children in the order they were first started."""
        self._send, self._recv = anyio.create_memory_object_stream[Output](1024)
        self._locks = {r.node: anyio.Lock() for r in runs}
        self._stdout_ok = True
        self._grace_scope: anyio.CancelScope | None = None
        self.error = ""
        """Why rap up gave up, when it did."""
        self.args = ""
        """What ``rap health`` and ``rap down`` need besides the model (``--run-dir``)."""

    # -- output ------------------------------------------------------------------------

    async def say(self, text: str, child: Child | None = None) -> None:
        """A line of rap up's own on stdout (and in ``child``'s log)."""
        raw = f"[rap up] {text}\n".encode() if child is not None else b""
        await self._send.send(
            (child.log if child else None, raw, f"{'rap'.ljust(self._pad)} | {text}\n")
        )

    async def _writer(self) -> None:
        async with self._recv:
            async for item in self._recv:
                batch = [item]
                while True:
                    try:
                        batch.append(self._recv.receive_nowait())
                    except (anyio.WouldBlock, anyio.EndOfStream):
                        break
                await anyio.to_thread.run_sync(self._write, batch)

    def _write(self, batch: list[Output]) -> None:
        logs: set[IO[bytes]] = set()
        for log, raw, _ in batch:
            if log is not None and raw:
                log.write(raw)
                logs.add(log)
        for log in logs:
            with contextlib.suppress(OSError):
                log.flush()
        if self._stdout_ok:
            try:
                sys.stdout.write("".join(text for _, _, text in batch))
                sys.stdout.flush()
            except OSError:  # nobody reads our output any more (a closed pipe)
                self._stdout_ok = False

    async def _pump(self, child: Child, stream: Any) -> None:
        buf = b""
        async for chunk in stream:
            buf += chunk
            *lines, buf = buf.split(b"\n")
            if len(buf) > MAX_LINE:
                lines.append(buf)
                buf = b""
            if lines:
                await self._emit(child, lines)
        if buf:
            await self._emit(child, [buf])

    async def _emit(self, child: Child, lines: list[bytes]) -> None:
        texts = [line.decode(errors="replace").rstrip("\r") for line in lines]
        if child.spec.role == "router" and any(_router_ready(t) for t in texts):
            child.ready.set()
        for t in reversed(texts):
            if t.strip():
                child.tail = t.strip()
                break
        raw = b"".join(line + b"\n" for line in lines)
        text = "".join(f"{child.label} | {t}\n" for t in texts)
        await self._send.send((child.log, raw, text))

    # -- state -------------------------------------------------------------------------

    def _snapshot(self, node: str) -> dict[str, Any]:
        run = next(r for r in self.runs if r.node == node)
        return {
            "version": 1,
            "state": self.state,
            "model": str(self.model),
            "system": self.system,
            "node": node,
            "nodes": [r.node for r in self.runs],
            "supervisor": {"pid": os.getpid(), "identity": self.identity},
            "started": self.started,
            "updated": time.time(),
            "router": run.local,
            "dashboard": run.dashboard or None,
            "router_config": run.paths.router_config,
            "client_config": run.paths.client_config,
            "children": [
                {
                    "name": c.name,
                    "role": c.spec.role,
                    "pid": c.proc.pid if c.alive() and c.proc is not None else None,
                    "identity": c.identity if c.alive() else None,
                    "state": c.state,
                    "restarts": c.restarts,
                    "last_exit": c.last_exit,
                    "log": str(c.log_path),
                    "metrics": c.spec.metrics or None,
                    "argv": c.argv,
                }
                for c in self.children
                if c.node == node
            ],
        }

    async def save(self, node: str | None = None) -> None:
        """Write the state file of ``node`` (of every node when None)."""
        for r in self.runs:
            if node is not None and r.node != node:
                continue
            async with self._locks[r.node]:
                text = json.dumps(self._snapshot(r.node), indent=2) + "\n"
                await anyio.to_thread.run_sync(_replace, r.dir / STATE_FILE, text)

    # -- one child ---------------------------------------------------------------------

    async def _keep(self, child: Child) -> None:
        """Run ``child`` until it is stopped, restarting it with backoff."""
        delay = BACKOFF_FIRST
        try:
            while not child.stopping:
                code, uptime = await self._run_once(child)
                child.wake = anyio.Event()  # before any await: a stop from now on sets it
                if child.stopped():
                    break
                if child.spec.role == "router" and not child.ready.is_set():
                    child.state = "failed"  # it never listened: rap up gives up (see _start)
                    break
                if uptime >= BACKOFF_RESET:
                    delay = BACKOFF_FIRST
                child.state = "backoff"
                await self.say(
                    f"{child.title} exited with code {code}{_meaning(code)} after "
                    f"{uptime:.1f} s; restarting it in {delay:g} s "
                    f"(restart {child.restarts + 1})",
                    child,
                )
                await self.save(child.node)
                with anyio.move_on_after(delay):
                    await child.wake.wait()
                delay = min(delay * 2, BACKOFF_MAX)
                if not child.stopping:
                    child.restarts += 1
        finally:
            if child.state != "failed":
                child.state = "stopped"
            child.done.set()

    async def _run_once(self, child: Child) -> tuple[int, float]:
        """Start ``child``'s process and wait for it to exit: (exit code, seconds up)."""
        child.state = "starting"
        began = time.monotonic()
        try:
            proc = await anyio.open_process(
                child.argv,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                cwd=child.cwd,
                env=child.env,
                start_new_session=True,  # Ctrl-C reaches rap up only: it stops them in order
            )
        except OSError as exc:
            await self.say(
                f"cannot start {child.title} ({' '.join(child.argv)}): {exc.strerror or exc} - "
                "check the command (run: in the model)",
                child,
            )
            child.last_exit = 127
            child.spawned.set()
            return 127, 0.0
        child.proc = proc
        if child.stopping:
            child.signal(signal.SIGTERM)
        child.identity = await anyio.to_thread.run_sync(_identity, proc.pid)
        child.state = "running"
        await self.say(f"started {child.title} (pid {proc.pid}): {' '.join(child.argv)}", child)
        await self.save(child.node)
        child.spawned.set()
        try:
            async with anyio.create_task_group() as tg:
                pumped = anyio.Event()

                async def pump() -> None:
                    try:
                        if proc.stdout is not None:
                            await self._pump(child, proc.stdout)
                    finally:
                        pumped.set()

                tg.start_soon(pump)
                code = await proc.wait()
                with anyio.move_on_after(OUTPUT_LINGER):
                    await pumped.wait()
                tg.cancel_scope.cancel()
        finally:
            if proc.returncode is None:  # cancelled: never leave a process behind
                child.signal(signal.SIGKILL)
                with anyio.CancelScope(shield=True):
                    await proc.wait()
            with anyio.CancelScope(shield=True):
                await proc.aclose()
        child.last_exit = code
        return code, time.monotonic() - began

    async def _stop(self, child: Child) -> None:
        child.stopping = True
        child.wake.set()
        if child.alive():
            child.state = "stopping"
            await self.save(child.node)
            child.signal(signal.SIGTERM)
        with anyio.move_on_after(self.grace) as scope:
            self._grace_scope = scope
            await child.done.wait()
        self._grace_scope = None
        if not child.done.is_set():
            await self.say(
                f"{child.title} did not stop within {self.grace:g} s of SIGTERM; killing it", child
            )
            child.signal(signal.SIGKILL)
            await child.done.wait()
        if child.proc is not None:
            await self.say(f"stopped {child.title} (exit code {child.last_exit})", child)
        await self.save(child.node)

    # -- the whole --------------------------------------------------------------------

    async def run(self) -> int:
        """Start everything, supervise until SIGTERM/SIGINT, stop; the exit code."""
        self.identity = await anyio.to_thread.run_sync(_identity, os.getpid())
        for c in self.children:
            c.log = await anyio.to_thread.run_sync(c.log_path.open, "ab")
        code = OK
        try:
            async with anyio.create_task_group() as outer:
                outer.start_soon(self._writer)
                try:
                    async with anyio.create_task_group() as tg:
                        stop = anyio.Event()
                        with anyio.open_signal_receiver(
                            signal.SIGTERM, signal.SIGINT, signal.SIGHUP
                        ) as signals:
                            tg.start_soon(self._signals, signals, stop)
                            await self.save()
                            code = await self._start(tg, stop)
                            if code == OK:
                                self.state = "running"
                                await self.save()
                                await self._report_up()
                                await stop.wait()
                            self.state = "stopping"
                            await self.save()
                            for child in reversed(self.order):
                                await self._stop(child)
                            tg.cancel_scope.cancel()
                finally:
                    self.state = "stopped"
                    with anyio.CancelScope(shield=True):
                        await self.save()
                        await self.say("stopped" if code == OK else "gave up")
                    self._send.close()
        finally:
            for c in self.children:
                if c.log is not None:
                    c.log.close()
        return code

    async def _signals(self, signals: Any, stop: anyio.Event) -> None:
        async for signum in signals:
            name = signal.Signals(signum).name
            if not stop.is_set():
                await self.say(f"received {name}: stopping every process, last started first")
                stop.set()
            else:
                await self.say(f"received {name} again: killing what has not stopped yet")
                self.grace = 0.0
                if self._grace_scope is not None:
                    self._grace_scope.cancel()

    async def _start(self, tg: TaskGroup, stop: anyio.Event) -> int:
        routers = [c for c in self.children if c.spec.role == "router"]
        for router in routers:
            self.order.append(router)
            tg.start_soon(self._keep, router)
            with anyio.move_on_after(ROUTER_START):
                await _first(router.ready, router.done, stop)
            if stop.is_set():
                return OK
            if not router.ready.is_set():
                why = (
                    f"exited with code {router.last_exit}"
                    if router.done.is_set()
                    else f"did not listen within {ROUTER_START:g} s"
                )
                await self.say(
                    f"the router of compute node {router.node} {why}: {router.tail or '-'}; "
                    f"its output is in {router.log_path}"
                )
                self.error = (
                    f"the router of compute node {router.node} {why} "
                    f"({router.tail or 'no output'}) - see {router.log_path}; a listen "
                    "endpoint that is taken: free it or change the node's listen endpoints"
                )
                return FAILED
        for child in self.children:
            if child.spec.role != "router" and not stop.is_set():
                self.order.append(child)
                tg.start_soon(self._keep, child)
        for child in self.order:  # each has been started (or tried): up.json has its pid
            await _first(child.spawned, child.done, stop)
        return OK

    async def _report_up(self) -> None:
        for r in self.runs:
            listen = ", ".join(r.router["listen"]["endpoints"])
            names = ", ".join(p.name for p in r.processes)
            await self.say(
                f"compute node {r.node} is up: its router listens on {listen}; processes: "
                f"{names}; logs in {r.dir / 'logs'}"
            )
        for r in self.runs:
            if r.dashboard:
                await self.say(f"dashboard: {r.dashboard}")
        first = self.runs[0].node
        await self.say(
            f"check it with 'rap health {self.model} --node {first}{self.args}'; stop it with "
            f"Ctrl-C or 'rap down {self.model}{self.args}'"
        )


def _router_ready(line: str) -> bool:
    from .router import READY

    return READY in line


async def _first(*events: anyio.Event) -> None:
    """Return once any of ``events`` is set."""
    async with anyio.create_task_group() as tg:

        async def one(event: anyio.Event) -> None:
            await event.wait()
            tg.cancel_scope.cancel()

        for e in events:
            tg.start_soon(one, e)


def _replace(path: Path, text: str) -> None:
    """Write ``path`` atomically (readers never see half a file)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


# -- commands ----------------------------------------------------------------------------------


def up(
    model: ModelArg,
    node: Annotated[
        list[str] | None,
        typer.Option(
            "--node",
            "-n",
            help="A compute node to run, repeatable (default: the only one the model has).",
            show_default=False,
        ),
    ] = None,
    all_nodes: Annotated[
        bool, typer.Option("--all", help="Run every compute node, their routers linked.")
    ] = False,
    address: Annotated[
        list[str] | None,
        typer.Option(
            "--address",
            help="NODE=HOST: where compute node NODE is (an endpoint naming NODE as host "
            "goes there), repeatable. With --all every node is on 127.0.0.1 unless given.",
            show_default=False,
        ),
    ] = None,
    run_dir: RunDirOpt = None,
    log_level: Annotated[str, typer.Option("--log-level", help="The processes' logging level.")] = (
        "INFO"
    ),
    grace: Annotated[
        float,
        typer.Option("--grace", help="Seconds a process has to stop after SIGTERM before SIGKILL."),
    ] = 10.0,
    certs: Annotated[
        Path | None,
        typer.Option(
            "--certs",
            help="The certificates `rap certs` wrote, used when the model says fabric: "
            "{tls: true} (default: `<model folder>/certs`).",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Run compute nodes of a model on this machine: for each, its Zenoh router, then
    knowledge, the runner, the trust checkers and the `run:` commands mapped there, as
    Zenoh clients of the router. Their output is shown prefixed with the process's name
    and kept in `<run-dir>/<node>/logs/`. A process that exits is restarted (with a
    growing delay). Ctrl-C or SIGTERM (`rap down`) stops everything, last started first.
    Beside knowledge runs the system's adaptation manager: its dashboard's address
    (loopback, a free port) is printed (`dashboard: http://127.0.0.1:PORT/`) and kept in
    that node's `up.json`.
    With `fabric: {tls: true}` in the model, the routers link over mutual TLS, each with
    its node's certificate from --certs (`rap certs MODEL` makes them); a node's own
    processes reach its router on loopback tcp.
    Exit 0 when stopped so, 1 when a router cannot start, 2 for a bad model or usage.

    Example: `rap up examples/lidar_occlusion/model.yaml --all`"""
    file, doc = _load(model)
    plan = doc.plan
    if all_nodes and node:
        usage("give --node or --all, not both")
    if all_nodes:
        nodes = list(plan.compute_nodes)
    elif node:
        nodes = _check_nodes(doc, node)
    else:
        nodes = [_one_node(doc, None)]
    addresses = _addresses(doc, address or [])
    if all_nodes:
        addresses = {n: addresses.get(n, "127.0.0.1") for n in plan.compute_nodes}
    level = _log_level(log_level)
    if grace < 0:
        usage(f"--grace {grace:g}: give a number of seconds >= 0")
    base = (run_dir or _default_run_dir(file, plan)).resolve()
    cert_dir = (certs or file.parent / "certs").resolve()
    if plan.fabric.tls:
        for n in nodes:
            missing = TlsFiles.of(cert_dir, n).missing()
            if missing:
                usage(
                    f"{doc.where(('fabric', 'tls'))}: the model says fabric.tls, but compute "
                    f"node {n} has no certificate in {cert_dir} (missing: "
                    f"{', '.join(Path(m).name for m in missing)}) - run rap certs {model}"
                    + (f" -o {certs}" if certs is not None else "")
                    + " (or give --certs DIR)"
                )
    elif certs is not None:
        typer.echo(f"note: {file} does not say fabric: {{tls: true}} - --certs is not used")
    for n in nodes:
        state = read_state(base / n / STATE_FILE)
        if _running(state):
            assert state is not None
            usage(
                f"compute node {n} is already up (rap up pid {state['supervisor']['pid']}, "
                f"{base / n / STATE_FILE}) - stop it first: rap down {model} --node {n}"
            )
        left = _left_behind(state)
        if left:
            usage(
                f"compute node {n}: an earlier rap up died without stopping its processes "
                f"({', '.join(f'{name} pid {pid}' for name, pid in left)}) - stop them "
                f"first: rap down {model} --node {n}"
                + (f" --run-dir {run_dir}" if run_dir is not None else "")
            )
    try:
        runs = plan_run(
            doc,
            file,
            nodes,
            base,
            addresses=addresses,
            log_level=level,
            link=True,
            certs=cert_dir,
        )
    except KeyError as exc:
        usage(str(exc.args[0]) if exc.args else str(exc))
    try:
        if run_dir is None:
            base.parent.mkdir(parents=True, exist_ok=True)
            ignore = base.parent / ".gitignore"
            if not ignore.exists():
                ignore.write_text("# rap up's run directories\n*\n", encoding="utf-8")
        _write_configs(runs, plan.system)
    except OSError as exc:
        usage(f"{base}: cannot write the run directory ({exc.strerror}) - choose --run-dir")
    extra = f" --run-dir {base}" if run_dir is not None else ""
    code, error = anyio.run(_supervise, runs, file, plan.system, grace, extra)
    if error:
        typer.echo(f"rap: error: {error}", err=True)
    raise typer.Exit(code)


async def _supervise(
    runs: list[NodeRun], model: Path, system: str, grace: float, args: str
) -> tuple[int, str]:
    sup = Supervisor(runs, model=model, system=system, grace=grace)
    sup.args = args
    code = await sup.run()
    return code, sup.error


def down(
    model: ModelArg,
    node: Annotated[
        list[str] | None,
        typer.Option(
            "--node", "-n", help="A compute node to stop (default: all).", show_default=False
        ),
    ] = None,
    run_dir: RunDirOpt = None,
    timeout: Annotated[
        float, typer.Option("--timeout", help="Seconds to wait for rap up to stop.")
    ] = 60.0,
) -> None:
    """Stop the `rap up` that runs compute nodes of a model (SIGTERM; it stops its
    processes, last started first) and wait until it has exited. Exit 0 when stopped or
    when nothing runs, 1 when it did not stop within --timeout."""
    file, doc = _load(model)
    nodes = _check_nodes(doc, node) if node else list(doc.plan.compute_nodes)
    base = (run_dir or _default_run_dir(file, doc.plan)).resolve()
    supervisors: dict[int, list[str]] = {}
    leftovers: list[tuple[str, int]] = []
    for n in nodes:
        path = base / n / STATE_FILE
        state = read_state(path)
        if state is None or state.get("state") == "stopped":
            continue
        if _running(state):
            supervisors.setdefault(int(state["supervisor"]["pid"]), []).append(n)
            continue
        # rap up died without stopping its processes (SIGKILL): stop what it left
        leftovers.extend((f"{n}/{name}", pid) for name, pid in _left_behind(state))
        state["state"] = "stopped"
        _replace(path, json.dumps(state, indent=2) + "\n")
        typer.echo(f"compute node {n}: its rap up is gone (it did not stop cleanly)")
    if not supervisors and not leftovers:
        typer.echo(f"nothing to stop: no rap up runs compute node(s) {', '.join(nodes)} ({base})")
        raise typer.Exit(OK)
    for pid, names in supervisors.items():
        typer.echo(f"stopping rap up (pid {pid}) of compute node(s) {', '.join(names)}")
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGTERM)
    for label, pid in leftovers:
        typer.echo(f"stopping {label} (pid {pid}), left behind")
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, signal.SIGTERM)
    waiting = {pid: ", ".join(names) for pid, names in supervisors.items()}
    waiting.update({pid: label for label, pid in leftovers})
    deadline = time.monotonic() + timeout
    while waiting and time.monotonic() < deadline:
        for pid in list(waiting):
            if _identity(pid) is None or _zombie(pid):
                del waiting[pid]
        if waiting:
            time.sleep(0.1)  # a command-line wait for other processes (no event loop here)
    if waiting:
        failed(
            "still running after "
            f"{timeout:g} s: "
            + "; ".join(f"pid {pid} ({what})" for pid, what in waiting.items())
            + f" - see {base}/<node>/logs, wait longer (--timeout) or kill it"
        )
    typer.echo("stopped")
    raise typer.Exit(OK)


def _zombie(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
            return f.read().rpartition(")")[2].split()[:1] == ["Z"]
    except OSError:
        return False


def health(
    model: ModelArg,
    node: Annotated[
        str | None,
        typer.Option(
            "--node", "-n", help="The compute node (default: the only one).", show_default=False
        ),
    ] = None,
    timeout: Annotated[
        float, typer.Option("--timeout", help="Seconds to wait for the Nodes' liveliness.")
    ] = 5.0,
    connect: Annotated[
        list[str] | None,
        typer.Option(
            "--connect",
            help="A Zenoh endpoint to reach the fabric through (a router), repeatable.",
            show_default=False,
        ),
    ] = None,
    run_dir: RunDirOpt = None,
    certs: CertsOpt = None,
    identity: AsOpt = None,
) -> None:
    """Exit 0 when every Node of a compute node's share (its components with a
    `module:`, and knowledge when it hosts it) is alive on the fabric, else 1, naming
    the missing ones. The fabric is reached through --connect, else RAP_ZENOH_CONFIG
    (inside a container: the node's client config), else the router of the `rap up`
    that runs the node. A tls/ endpoint (fabric: {tls: true}) wants a certificate:
    --as NAME and --certs DIR (`rap certs`).

    Example: `rap health model.yaml --node edge --connect tls/10.0.0.2:7447 --as ops`"""
    from .reach import _tls

    file, doc = _load(model)
    name = _one_node(doc, node)
    if timeout <= 0:
        usage(f"--timeout {timeout:g}: give a number of seconds > 0")
    endpoints = list(connect or [])
    from rap_sdk.entry import EntryError, check_endpoints

    try:
        check_endpoints("--connect", endpoints)
    except EntryError as exc:
        usage(exc.message)
    tls = None
    if endpoints:
        os.environ.pop(CONFIG_ENV, None)  # --connect says where: no overlay
        where = ", ".join(endpoints)
        tls = _tls(endpoints, file, certs, identity)
    elif os.environ.get(CONFIG_ENV):
        where = f"{CONFIG_ENV}={os.environ[CONFIG_ENV]}"
    else:
        base = (run_dir or _default_run_dir(file, doc.plan)).resolve()
        path = base / name / STATE_FILE
        state = read_state(path)
        if not _running(state) or state is None or not isinstance(state.get("router"), str):
            usage(
                f"no rap up runs compute node {name} ({path}) and {CONFIG_ENV} is not set - "
                f"start it (rap up {model} --node {name}) or give --connect ENDPOINT"
            )
        endpoints = [state["router"]]
        where = f"the router of rap up at {endpoints[0]}"
    expected = expected_nodes(doc.plan, name)
    code = anyio.run(_health, doc.plan.system, name, expected, endpoints, where, timeout, tls)
    raise typer.Exit(code)


async def _health(
    system: str,
    node: str,
    expected: list[str],
    endpoints: list[str],
    where: str,
    timeout: float,
    tls: TlsFiles | None = None,
) -> int:
    from rap_sdk import FabricError, ZenohConfig, ZenohFabric

    extra = {"transport": client_config("", tls)["transport"]} if tls is not None else {}
    conf = ZenohConfig(mode="client", listen=[], connect=endpoints, extra=extra)
    seen: set[str] = set()
    try:
        async with ZenohFabric(conf) as fabric:
            with fabric.watch_liveliness(keys.pattern(system, keys.Kind.ALIVE)) as watch:
                with anyio.move_on_after(timeout):
                    while not set(expected) <= seen:
                        change = await watch.get()
                        try:
                            name = keys.parse(change.key).name
                        except keys.KeyError_:
                            continue
                        if change.alive:
                            seen.add(name)
                        else:
                            seen.discard(name)
    except FabricError as exc:
        typer.echo(
            f"rap: error: compute node {node}: cannot reach the fabric through {where}: {exc} - "
            "is its router running (rap up)?",
            err=True,
        )
        return FAILED
    missing = [n for n in expected if n not in seen]
    if not expected:
        typer.echo(f"compute node {node}: no Nodes to check; the fabric is reachable ({where})")
        return OK
    if missing:
        alive = [n for n in expected if n in seen]
        typer.echo(
            f"compute node {node}: not alive within {timeout:g} s: {', '.join(missing)}"
            + (f" (alive: {', '.join(alive)})" if alive else "")
            + f"; see the logs of its processes (rap up's output, <run-dir>/{node}/logs)",
            err=True,
        )
        return FAILED
    typer.echo(f"compute node {node}: alive: {', '.join(expected)}")
    return OK


def register(app: typer.Typer) -> None:
    """Add ``rap up``, ``rap down`` and ``rap health`` to ``app``."""
    app.command("up")(up)
    app.command("down")(down)
    app.command("health")(health)
