"""Helpers of the I/O tests: a hand-written spec runner, a recording sink, a mosquitto and
a redis-server of the test's own. (No tests here.)"""

from __future__ import annotations

import math
import os
import subprocess
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import anyio
from anyio.abc import Process, TaskStatus
from anyio.streams.text import TextReceiveStream
from rap_schemas import TrustSpecStatus
from rap_sdk.testing import free_port, require_binary
from trust_checker.errors import EvalError, InputError, Problem, SpecError
from trust_checker.io.ports import OutputLike
from trust_checker.values import BOTTOM


@dataclass(frozen=True)
class FakeSpec:
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    period_ns: int | None = None


@dataclass(frozen=True)
class Out:
    stream: str
    tick: int
    value: object
    ts_ns: int | None


class FakeRunner:
    """Every output is the running total of the Int inputs so far (history that a swap
    carries over); an input "bottom" makes every output ⊥; the Str input "boom" fails the
    tick; a value that is not an Int or Str is refused (InputError)."""

    def __init__(self, spec: FakeSpec, total: int = 0, tick: int = 0) -> None:
        self.spec = spec
        self.total = total
        self.tick = tick
        self.steps: list[tuple[dict[str, object], int | None]] = []
        self._periodic_next: int | None = None

    @property
    def inputs(self) -> tuple[str, ...]:
        return self.spec.inputs

    @property
    def outputs(self) -> tuple[str, ...]:
        return self.spec.outputs

    def step(self, inputs: dict[str, object], ts_ns: int | None = None) -> list[Out]:
        for name, v in inputs.items():
            if name not in self.spec.inputs:
                raise InputError(f"unknown input {name!r}")
            if type(v) not in (int, str, bool):
                raise InputError(f"input {name!r}: not an Int: {v!r}")
        self.steps.append((dict(inputs), ts_ns))
        tick = self.tick
        self.tick += 1
        if "boom" in inputs.values():
            raise EvalError("boom", stream=self.spec.outputs[0], tick=tick)
        value: object = BOTTOM if "bottom" in inputs.values() else None
        self.total += sum(v for v in inputs.values() if type(v) is int)
        if value is None:
            value = self.total
        return [Out(o, tick, value, ts_ns) for o in self.spec.outputs]

    def swap(self, spec: Any) -> FakeRunner:
        assert isinstance(spec, FakeSpec)
        return FakeRunner(spec, self.total, self.tick)

    def next_due(self, ts: int) -> int | None:
        p = self.spec.period_ns
        if p is None:
            return None
        return (ts // p + 1) * p


def fake_loader(text: str, path: str) -> FakeSpec:
    """``in a b`` / ``out s`` lines; anything else is a SpecError at its line."""
    ins: list[str] = []
    outs: list[str] = []
    problems: list[Problem] = []
    for n, line in enumerate(text.splitlines(), 1):
        kind, _, names = line.partition(" ")
        if kind == "in":
            ins += names.split()
        elif kind == "out":
            outs += names.split()
        elif line.strip():
            problems.append(Problem(path, n, 1, f"unexpected {line!r}", line, "write in/out"))
    if problems:
        raise SpecError(problems)
    return FakeSpec(tuple(ins), tuple(outs))


@dataclass
class RecordingSink:
    outs: list[OutputLike] = field(default_factory=list)
    statuses: list[TrustSpecStatus] = field(default_factory=list)
    _changed: anyio.Event = field(default_factory=anyio.Event)

    async def outputs(self, outs: Sequence[OutputLike]) -> None:
        self.outs.extend(outs)
        self._changed.set()

    async def status(self, status: TrustSpecStatus) -> None:
        self.statuses.append(status)
        self._changed.set()

    async def wait_for(self, n_outs: int = 0, n_statuses: int = 0, timeout: float = 5.0) -> None:
        with anyio.fail_after(timeout):
            while len(self.outs) < n_outs or len(self.statuses) < n_statuses:
                self._changed = anyio.Event()
                await self._changed.wait()


@dataclass(frozen=True)
class BrokerTls:
    """The broker's TLS files (PEM); ``require_client``: clients must present a
    certificate of ``ca``."""

    ca: Path
    cert: Path
    key: Path
    require_client: bool = True


class Mosquitto:
    """A mosquitto broker of the test's own on a free loopback port. Its log is read
    all along (so that the pipe never fills) and kept for failure messages. With
    ``passwords`` (user -> password) anonymous clients are refused and the passwords are
    hashed into a password file by ``mosquitto_passwd -U``; with ``tls`` the listener
    is TLS only."""

    def __init__(
        self,
        directory: Path,
        port: int | None = None,
        *,
        passwords: dict[str, str] | None = None,
        tls: BrokerTls | None = None,
    ) -> None:
        self.binary = require_binary("mosquitto", hint="apt-get install mosquitto")
        self.port = port or free_port()
        self.conf = directory / "mosquitto.conf"
        lines = [f"listener {self.port} 127.0.0.1", "persistence false"]
        if (passwords or tls) and os.geteuid() == 0:
            # run as root, mosquitto becomes user 'mosquitto' before it opens the password
            # file and the certificates, which sit in the test's private folder
            lines.append("user root")
        self.password_file: Path | None = None
        if passwords:
            require_binary("mosquitto_passwd", hint="apt-get install mosquitto")
            self.password_file = directory / "mosquitto.passwd"
            self.password_file.write_text(
                "".join(f"{user}:{pw}\n" for user, pw in passwords.items()), encoding="utf-8"
            )
            lines += ["allow_anonymous false", f"password_file {self.password_file}"]
        else:
            lines.append("allow_anonymous true")
        if tls is not None:
            lines += [f"cafile {tls.ca}", f"certfile {tls.cert}", f"keyfile {tls.key}"]
            lines.append(f"require_certificate {'true' if tls.require_client else 'false'}")
        lines += ["log_dest stderr", "log_type all"]
        self.conf.write_text("\n".join(lines) + "\n", encoding="utf-8")
        self.log = ""
        self._proc: Process | None = None

    async def run(self, *, task_status: TaskStatus[None]) -> None:
        if self.password_file is not None:
            await anyio.run_process(["mosquitto_passwd", "-U", str(self.password_file)])
        self._proc = proc = await anyio.open_process(
            [self.binary, "-c", str(self.conf)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT
        )
        assert proc.stdout is not None
        started = False
        with anyio.fail_after(10) as scope:
            async for chunk in TextReceiveStream(proc.stdout):
                self.log = (self.log + chunk)[-20_000:]
                if not started and " running" in self.log:
                    started = True
                    scope.deadline = math.inf
                    task_status.started()
        if not started:
            raise RuntimeError(f"mosquitto did not start:\n{self.log}")

    async def stop(self) -> None:
        if self._proc is not None:
            proc, self._proc = self._proc, None
            if proc.returncode is None:
                proc.terminate()
            with anyio.fail_after(10):
                await proc.wait()
            await proc.aclose()


@asynccontextmanager
async def mosquitto(
    directory: Path,
    port: int | None = None,
    *,
    passwords: dict[str, str] | None = None,
    tls: BrokerTls | None = None,
) -> AsyncIterator[Mosquitto]:
    server = Mosquitto(directory, port, passwords=passwords, tls=tls)
    async with anyio.create_task_group() as tg:
        try:
            await tg.start(server.run)
            yield server
        finally:
            with anyio.CancelScope(shield=True):
                await server.stop()


class RedisServer:
    """A redis-server of the test's own on a free loopback port, configured by a file in
    the test's folder; no persistence. Its log is read all along (so that the pipe never
    fills) and kept for failure messages. ``password``: ``requirepass``; ``users``: ACL
    lines (``"checker on >pw ~* &* +@all"``; add ``"default off"`` to refuse anonymous
    clients); ``tls``: the port is TLS only (``tls.require_client``: clients must present
    a certificate of ``tls.ca``). :meth:`kill` ends it at once (SIGKILL); :meth:`run` starts
    it again on the same port."""

    def __init__(
        self,
        directory: Path,
        port: int | None = None,
        *,
        password: str | None = None,
        users: Sequence[str] = (),
        tls: BrokerTls | None = None,
    ) -> None:
        self.binary = require_binary("redis-server", hint="apt-get install redis-server")
        self.port = port or free_port()
        self.conf = directory / f"redis-{self.port}.conf"
        lines = [
            "bind 127.0.0.1",
            'save ""',
            "appendonly no",
            f"dir {directory}",
            'logfile ""',
        ]
        if tls is None:
            lines.append(f"port {self.port}")
        else:
            lines += [
                "port 0",
                f"tls-port {self.port}",
                f"tls-cert-file {tls.cert}",
                f"tls-key-file {tls.key}",
                f"tls-ca-cert-file {tls.ca}",
                f"tls-auth-clients {'yes' if tls.require_client else 'no'}",
            ]
        if password is not None:
            lines.append(f"requirepass {password}")
        lines += [f"user {user}" for user in users]
        self.conf.write_text("\n".join(lines) + "\n", encoding="utf-8")
        self.log = ""
        self._proc: Process | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    async def run(self, *, task_status: TaskStatus[None]) -> None:
        self._proc = proc = await anyio.open_process(
            [self.binary, str(self.conf)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT
        )
        assert proc.stdout is not None
        started = False
        with anyio.fail_after(10) as scope:
            try:
                async for chunk in TextReceiveStream(proc.stdout):
                    self.log = (self.log + chunk)[-20_000:]
                    if not started and "Ready to accept connections" in self.log:
                        started = True
                        scope.deadline = math.inf
                        task_status.started()
            except (anyio.ClosedResourceError, anyio.BrokenResourceError):
                pass  # stopped (or killed) while its last lines were read
        if not started:
            raise RuntimeError(f"redis-server did not start:\n{self.log}")

    async def kill(self) -> None:
        """End the server at once, as a crash would (SIGKILL)."""
        await self.stop(kill=True)

    async def stop(self, *, kill: bool = False) -> None:
        if self._proc is not None:
            proc, self._proc = self._proc, None
            if proc.returncode is None and kill:
                proc.kill()
            elif proc.returncode is None:
                proc.terminate()
            with anyio.fail_after(10):
                await proc.wait()
            await proc.aclose()


@asynccontextmanager
async def redis_server(
    directory: Path,
    port: int | None = None,
    *,
    password: str | None = None,
    users: Sequence[str] = (),
    tls: BrokerTls | None = None,
) -> AsyncIterator[RedisServer]:
    server = RedisServer(directory, port, password=password, users=users, tls=tls)
    async with anyio.create_task_group() as tg:
        try:
            await tg.start(server.run)
            yield server
        finally:
            with anyio.CancelScope(shield=True):
                await server.stop()
