"""Shared by the fault scenarios: model copies, ``rap up`` as a child with timestamped
output, the observer, a Redis server of our own, progress lines."""

from __future__ import annotations

import contextlib
import json
import re
import shutil
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import anyio
import yaml
from anyio.abc import Process
from rap_sdk.fabric import free_port

from ..report import ROOT

__all__ = [
    "MODEL",
    "SYSTEM",
    "Lines",
    "Observer",
    "RapUp",
    "RedisServer",
    "ScenarioError",
    "observer",
    "rap_up",
    "say",
    "write_model",
]

MODEL = ROOT / "examples" / "lidar_occlusion" / "model.yaml"
SYSTEM = "demo"
_T0 = time.monotonic()
_STARTED = re.compile(r"\| started (?:(?P<node>[\w.-]+)/)?(?P<name>[\w.-]+) \(pid (?P<pid>\d+)\)")


class ScenarioError(RuntimeError):
    """A scenario could not be carried out (not a missed target: those are figures)."""


def say(msg: str) -> None:
    """A progress line on stderr, with the seconds since the run started."""
    print(f"[{time.monotonic() - _T0:7.1f} s] {msg}", file=sys.stderr, flush=True)


def rap_command() -> str:
    rap = Path(sys.executable).with_name("rap")
    if not rap.exists():
        raise ScenarioError(f"{rap}: the rap command is not installed next to {sys.executable}")
    return str(rap)


# -- the model ---------------------------------------------------------------------------


def write_model(
    folder: Path,
    *,
    period: float | None = 1.0,
    backend: str | None = None,
    redis_url: str | None = None,
    tls_operators: Sequence[str] = (),
    simulator: bool = True,
    port: int | None = None,
) -> Path:
    """A copy of the lidar model in ``folder``: the edge's router on a free port (or
    ``port``), the simulator in a world whose occlusion changes every ``period`` s (so
    that the loop has something new to plan all the time; None: the model's own world),
    ``backend`` for knowledge, ``tls_operators`` to turn TLS on with those operators,
    and the simulator left out with ``simulator=False``."""
    from sim_world.world import default_world_path

    folder.mkdir(parents=True, exist_ok=True)
    model: dict[str, Any] = yaml.safe_load(MODEL.read_text())
    ep = f"tcp/edge:{port or free_port()}"
    model["compute_nodes"]["robot"]["connect"] = [ep]
    model["compute_nodes"]["edge"]["listen"] = [ep]
    if backend is not None:
        kb: dict[str, Any] = {"backend": backend, "node": "edge"}
        if redis_url is not None:
            kb["url"] = redis_url
        model["knowledge"] = kb
    if tls_operators:
        model["fabric"] = {"tls": True, "operators": list(tls_operators)}
    if not simulator:
        del model["components"]["robot"]
    elif period is not None:
        world = yaml.safe_load(default_world_path().read_text())
        world["occlusions"] = [{"robot": "tb1", "mode": "random", "period": period, "t_start": 1.0}]
        world_path = folder / "changing_world.yaml"
        world_path.write_text(yaml.safe_dump(world))
        run = model["components"]["robot"]["run"]
        run[run.index("--world") + 1] = str(world_path)
    out = folder / "model.yaml"
    out.write_text(yaml.safe_dump(model, sort_keys=False))
    return out


# -- output lines with their time --------------------------------------------------------


class Lines:
    """A child's stdout, line by line, each with ``time.monotonic()`` at arrival."""

    def __init__(self, proc: Process, name: str) -> None:
        self.proc = proc
        self.name = name
        self.items: list[tuple[float, str]] = []
        self._arrived = anyio.Event()
        self.ended = False

    async def pump(self) -> None:
        assert self.proc.stdout is not None
        buf = b""
        try:
            async for chunk in self.proc.stdout:
                *lines, buf = (buf + chunk).split(b"\n")
                now = time.monotonic()
                self.items += [(now, x.decode(errors="replace")) for x in lines]
                self._wake()
        finally:
            if buf:
                self.items.append((time.monotonic(), buf.decode(errors="replace")))
            self.ended = True
            self._wake()

    def _wake(self) -> None:
        self._arrived.set()
        self._arrived = anyio.Event()

    async def first(
        self, pred: Callable[[float, str], bool], *, after: int = 0, timeout: float = 30.0
    ) -> int:
        """The index of the first line from ``after`` on that ``pred(t, text)`` accepts."""
        i = after
        with anyio.fail_after(timeout):
            while True:
                arrived = self._arrived
                for j in range(i, len(self.items)):
                    if pred(*self.items[j]):
                        return j
                i = len(self.items)
                if self.ended:
                    tail = "\n".join(x for _, x in self.items[-40:])
                    raise ScenarioError(
                        f"{self.name} ended (exit code {self.proc.returncode}) without the "
                        f"line waited for; its last output:\n{tail}"
                    )
                await arrived.wait()

    def tail(self, n: int = 40) -> str:
        return "\n".join(x for _, x in self.items[-n:])


# -- rap up ------------------------------------------------------------------------------


@dataclass
class RapUp:
    """A ``rap up`` this run started, and its output."""

    model: Path
    run: Path
    lines: Lines
    nodes: tuple[str, ...]

    def state(self, node: str) -> dict[str, Any]:
        data = json.loads((self.run / node / "up.json").read_text())
        assert isinstance(data, dict)
        return data

    def child(self, node: str, name: str) -> dict[str, Any]:
        for c in self.state(node)["children"]:
            if c["name"] == name:
                assert isinstance(c, dict)
                return c
        raise ScenarioError(f"rap up runs no process {name!r} on compute node {node}")

    def router(self, node: str) -> str:
        """The loopback endpoint of ``node``'s router, where its processes connect."""
        return str(self.state(node)["router"])

    def restarted(self, node: str, name: str, after: float) -> Callable[[float, str], bool]:
        """A predicate for rap up's line that it started ``node``/``name`` again."""

        def pred(t: float, text: str) -> bool:
            m = _STARTED.search(text)
            return (
                m is not None and t >= after and m["name"] == name and (m["node"] in (None, node))
            )

        return pred

    def text(self, node: str, process: str) -> str:
        """The log rap up keeps of ``process`` on ``node``."""
        path = self.run / node / "logs" / f"{process}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def jsonl(self, node: str, process: str) -> list[dict[str, Any]]:
        """The JSON-lines log of a RAP service of ``node``."""
        path = self.run / node / "logs" / f"{process}.jsonl"
        out: list[dict[str, Any]] = []
        if not path.exists():
            return out
        for line in path.read_text(errors="replace").splitlines():
            with contextlib.suppress(ValueError):
                rec = json.loads(line)
                if isinstance(rec, dict):
                    out.append(rec)
        return out


async def _stop(proc: Process, grace: float = 30.0) -> None:
    with anyio.CancelScope(shield=True):
        if proc.returncode is None:
            proc.terminate()
            with anyio.move_on_after(grace):
                await proc.wait()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


@contextlib.asynccontextmanager
async def rap_up(
    model: Path,
    run: Path,
    *,
    node: str | None = None,
    args: Sequence[str] = (),
    prefix: Sequence[str] = (),
    timeout: float = 60.0,
) -> AsyncIterator[RapUp]:
    """``rap up MODEL --all`` (or ``--node NODE``), run through ``prefix`` (``ip netns exec
    NS``), until its compute nodes are up; ``rap down`` on the way out (SIGTERM, then
    SIGKILL, if that does not stop it)."""
    rap = rap_command()
    which = ["--node", node] if node else ["--all"]
    nodes = (node,) if node else ("robot", "edge")
    argv = [*prefix, rap, "up", str(model), *which, "--run-dir", str(run), *args]
    async with (
        await anyio.open_process(argv, stderr=subprocess.STDOUT, cwd=ROOT) as proc,
        anyio.create_task_group() as tg,
    ):
        lines = Lines(proc, "rap up")
        tg.start_soon(lines.pump)
        try:
            for n in nodes:
                said = f"compute node {n} is up"

                def is_up(_t: float, text: str, said: str = said) -> bool:
                    return said in text

                await lines.first(is_up, timeout=timeout)
            yield RapUp(model, run, lines, nodes)
        finally:
            with anyio.CancelScope(shield=True):
                down = [rap, "down", str(model), "--run-dir", str(run)]
                if node:
                    down += ["--node", node]
                with anyio.move_on_after(60):
                    await anyio.run_process(down, check=False, stderr=subprocess.STDOUT)
                with anyio.move_on_after(30):
                    await proc.wait()
                await _stop(proc)
                tg.cancel_scope.cancel()


# -- the observer ------------------------------------------------------------------------


@dataclass
class Observer:
    """What ``bench.faults.observer`` saw (see its docstring)."""

    lines: Lines
    events: list[dict[str, Any]] = field(default_factory=list)
    _parsed: int = 0

    def _parse(self) -> None:
        for _, text in self.lines.items[self._parsed :]:
            with contextlib.suppress(ValueError):
                rec = json.loads(text)
                if isinstance(rec, dict):
                    self.events.append(rec)
        self._parsed = len(self.lines.items)

    def seen(self) -> list[dict[str, Any]]:
        self._parse()
        return self.events

    def plans(self, since: float = 0.0, until: float = float("inf")) -> list[dict[str, Any]]:
        return [e for e in self.seen() if e["kind"] == "plan" and since <= e["t"] < until]

    async def next(self, kind: str, after: float, timeout: float) -> dict[str, Any] | None:
        """The first ``kind`` line seen at or after ``after`` (None: not within
        ``timeout`` s)."""

        def pred(_t: float, text: str) -> bool:
            try:
                rec = json.loads(text)
            except ValueError:
                return False
            return isinstance(rec, dict) and rec.get("kind") == kind and rec["t"] >= after

        try:
            i = await self.lines.first(pred, timeout=timeout)
        except TimeoutError:
            return None
        rec = json.loads(self.lines.items[i][1])
        assert isinstance(rec, dict)
        return rec

    def back(self, names: Sequence[str], after: float) -> float | None:
        """When every one of ``names`` had its liveliness token up again, going by the
        last change of each at or after ``after`` (None: one of them is not up)."""
        last: dict[str, tuple[float, bool]] = {}
        for e in self.seen():
            if e["kind"] == "alive" and e["t"] >= after and e["name"] in names:
                last[e["name"]] = (e["t"], bool(e["up"]))
        if set(last) != set(names) or not all(up for _, up in last.values()):
            return None
        return max(t for t, _ in last.values())

    async def wait_back(self, names: Sequence[str], after: float, timeout: float) -> float | None:
        """:meth:`back`, waited for as the observer's lines come (None: not in time)."""
        try:
            await self.lines.first(
                lambda _t, _s: self.back(names, after) is not None, timeout=timeout
            )
        except TimeoutError:
            return None
        return self.back(names, after)

    def executions(self, since: float = 0.0, until: float = float("inf")) -> dict[str, Any]:
        """Plans sent to the robot between ``since`` and ``until``, by plan id (the
        ``plan_uid`` of the verdict each one was caused by; the verdict's own uid when it
        was not seen) and how many were sent more than once."""
        verdicts = {e["uid"]: e for e in self.seen() if e["kind"] == "verdict"}
        by_plan: dict[str, list[str]] = {}
        unresolved = 0
        uids: dict[str, int] = {}
        for p in self.plans(since, until):
            v = verdicts.get(p["cause"])
            if v is None:
                unresolved += 1
            plan_id = v["plan_uid"] if v is not None else f"verdict:{p['cause']}"
            by_plan.setdefault(plan_id, []).append(p["uid"])
            uids[p["uid"]] = uids.get(p["uid"], 0) + 1
        twice = {k: len(v) for k, v in by_plan.items() if len(v) > 1}
        return {
            "plans_sent": sum(len(v) for v in by_plan.values()),
            "distinct_plans": len(by_plan),
            "executed_twice": len(twice),
            "executed_twice_ids": dict(list(twice.items())[:20]),
            "same_sample_twice": sum(1 for n in uids.values() if n > 1),
            "plans_without_verdict_seen": unresolved,
        }


@contextlib.asynccontextmanager
async def observer(
    endpoint: str, *, prefix: Sequence[str] = (), stderr: Path | None = None
) -> AsyncIterator[Observer]:
    argv = [*prefix, sys.executable, "-m", "bench.faults.observer", endpoint, SYSTEM]
    with contextlib.ExitStack() as files:
        err = files.enter_context(stderr.open("wb")) if stderr else subprocess.DEVNULL
        async with (
            await anyio.open_process(argv, stderr=err, cwd=ROOT) as proc,
            anyio.create_task_group() as tg,
        ):
            lines = Lines(proc, "observer")
            tg.start_soon(lines.pump)
            try:
                await lines.first(lambda _t, s: '"kind": "ready"' in s, timeout=30)
                yield Observer(lines)
            finally:
                await _stop(proc, grace=10)
                tg.cancel_scope.cancel()


# -- Redis of our own --------------------------------------------------------------------


class RedisServer:
    """A redis-server this run owns: a free loopback port, its own folder, append-only
    with an fsync per write (``--appendonly yes --appendfsync always``)."""

    def __init__(self, folder: Path) -> None:
        binary = shutil.which("redis-server")
        if binary is None:
            raise ScenarioError(
                "redis-server is not installed: the redis scenarios start their own "
                "(apt-get install redis-server)"
            )
        self.binary = binary
        self.folder = folder
        self.port = free_port()
        self.proc: Process | None = None
        self.starts = 0

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    async def start(self) -> None:
        await anyio.Path(self.folder).mkdir(parents=True, exist_ok=True)
        argv = [self.binary, "--port", str(self.port), "--bind", "127.0.0.1"]
        argv += ["--dir", str(self.folder), "--appendonly", "yes", "--appendfsync", "always"]
        argv += ["--save", "", "--protected-mode", "yes", "--daemonize", "no"]
        log = await anyio.to_thread.run_sync((self.folder / "redis.log").open, "ab")
        with log:
            self.proc = await anyio.open_process(argv, stdout=log, stderr=subprocess.STDOUT)
        self.starts += 1
        with anyio.fail_after(20):
            while not await self._ping():
                if self.proc.returncode is not None:
                    raise ScenarioError(
                        f"redis-server exited with {self.proc.returncode}; see "
                        f"{self.folder / 'redis.log'}"
                    )
                await anyio.sleep(0.05)  # polling its port until it answers

    async def _ping(self) -> bool:
        try:
            with anyio.fail_after(1):
                stream = await anyio.connect_tcp("127.0.0.1", self.port)
                async with stream:
                    await stream.send(b"PING\r\n")
                    return (await stream.receive(64)).startswith(b"+PONG")
        except (OSError, TimeoutError, anyio.EndOfStream):
            return False

    async def kill(self) -> None:
        """kill -9: what it had acknowledged must be in its append-only file."""
        if self.proc is not None and self.proc.returncode is None:
            self.proc.kill()
            await self.proc.wait()

    async def stop(self) -> None:
        if self.proc is not None:
            await _stop(self.proc, grace=10)
