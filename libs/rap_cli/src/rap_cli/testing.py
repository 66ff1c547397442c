"""Test helpers for whole systems run as a user runs them: ``rap up --all`` of a model,
as a child process, until the block ends (then ``rap down``, which must stop it all).

    copy = model_copy(LIDAR_MODEL, tmp_path)          # the edge's port made free
    async with rap_up(copy, tmp_path / "run") as out:  # both compute nodes are up
        await out.line("anomaly")
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path

import anyio
from rap_schemas import DeploymentPlan, load_plan
from rap_sdk.fabric import ZenohConfig, ZenohFabric, free_port, node_overlay
from rap_sdk.testing import OutputLines, stop_process

from .certs_cli import write_certs
from .deploy import TlsFiles, client_config, render_zenoh, router_config

__all__ = [
    "EDGE_ENDPOINT",
    "SecuredRouter",
    "model_copy",
    "rap_command",
    "rap_up",
    "secured_router",
]

EDGE_ENDPOINT = "tcp/edge:7447"
"""The lidar model's router endpoint (its edge compute node listens there)."""


def rap_command() -> str:
    """The ``rap`` command installed next to this Python."""
    rap = Path(sys.executable).with_name("rap")
    if not rap.exists():
        raise FileNotFoundError(f"{rap}: the rap command is not installed next to {sys.executable}")
    return str(rap)


def model_copy(
    model: Path, folder: Path, *, endpoint: str = EDGE_ENDPOINT, drop: Sequence[str] = ()
) -> Path:
    """A copy of ``model`` in ``folder`` whose ``endpoint`` (the port 7447 may be taken on
    this machine) is on a free port, without the lines of ``drop`` (each must be there)."""
    text = model.read_text()
    if text.count(endpoint) < 2:
        raise ValueError(f"{model}: {endpoint} is not its listen and connect endpoint")
    host = endpoint.rpartition(":")[0]
    text = text.replace(endpoint, f"{host}:{free_port()}")
    for part in drop:
        if part not in text:
            raise ValueError(f"{model}: {part!r} is not in it")
        text = text.replace(part, "")
    copy = folder / "model.yaml"
    copy.write_text(text)
    return copy


@asynccontextmanager
async def rap_up(
    model: Path,
    run: Path,
    *,
    nodes: Sequence[str] = ("robot", "edge"),
    args: Sequence[str] = (),
    timeout: float = 30.0,
) -> AsyncIterator[OutputLines]:
    """``rap up MODEL --all`` until every one of ``nodes`` is up; its output lines are
    yielded. On the way out ``rap down`` must exit 0 and ``rap up`` with it (asserted,
    after a block that ended normally); whatever happens, the process is stopped."""
    rap = rap_command()
    argv = [rap, "up", str(model), "--all", "--run-dir", str(run), *args]
    async with (
        await anyio.open_process(argv, stderr=subprocess.STDOUT) as up,
        anyio.create_task_group() as tg,
    ):
        out = OutputLines(up)
        tg.start_soon(out.pump)
        try:
            with anyio.fail_after(timeout):
                for node in nodes:
                    await out.line(f"compute node {node} is up")
            yield out
            down = await anyio.run_process(
                [rap, "down", str(model), "--run-dir", str(run)], check=False
            )
            assert down.returncode == 0, down.stdout.decode() + down.stderr.decode()
            with anyio.fail_after(timeout):
                assert await up.wait() == 0, str(out)
        finally:
            await stop_process(up)  # a failure: it still stops what it started


@dataclass
class SecuredRouter:
    """A router with mutual TLS and the access control derived from a model."""

    plan: DeploymentPlan
    certs: Path
    endpoint: str
    log: OutputLines
    """The router's output: its refusals, with the identity."""

    def session(self, identity: str) -> ZenohFabric:
        """A RAP process's session as ``identity`` (RAP_AS), as rap up configures it."""
        text = json.dumps(client_config(self.endpoint, secure=True))
        env = {"RAP_AS": identity, "RAP_CERTS": str(self.certs)}
        return ZenohFabric(node_overlay(ZenohConfig(), text, env=env))

    async def refusal(self, identity: str, what: str, key: str) -> str:
        """The router's log line refusing ``identity`` ``what`` on ``key``."""
        at = await self.log.line(f"refused: {identity} may not {what} (ingress) on {key}")
        return self.log.lines[at]


def _secure(model: Path, folder: Path, node: str) -> tuple[DeploymentPlan, Path, str, Path]:
    model.write_text(model.read_text() + "\nfabric:\n  tls: true\n  operators: [ops]\n")
    plan = load_plan(model).plan
    certs = folder / "certs"
    write_certs(plan, certs)
    endpoint = f"tls/127.0.0.1:{free_port()}"
    conf = router_config(plan, node, local=[endpoint], listen=[], tls=TlsFiles.of(certs, node))
    if conf["access_control"]["default_permission"] != "deny":
        raise AssertionError("the router's access control must deny by default")
    path = folder / "router.json5"
    path.write_text(render_zenoh(conf, title="test router"))
    return plan, certs, endpoint, path


@asynccontextmanager
async def secured_router(
    model: Path, folder: Path, *, node: str = "edge"
) -> AsyncIterator[SecuredRouter]:
    """``model`` (a file the caller may have edited) with TLS and operators ``[ops]``:
    certificates for it in ``folder/certs``, and compute node ``node``'s router on a free
    loopback port with the access control the model derives, until the block ends."""
    plan, certs, endpoint, path = await anyio.to_thread.run_sync(_secure, model, folder, node)
    async with (
        await anyio.open_process(
            [sys.executable, "-m", "rap_cli.router", "--config", str(path)],
            stderr=subprocess.STDOUT,
        ) as proc,
        anyio.create_task_group() as tg,
    ):
        log = OutputLines(proc, timeout=10)
        tg.start_soon(log.pump)
        try:
            await log.line("listening on")
            yield SecuredRouter(plan, certs, endpoint, log)
        finally:
            await stop_process(proc)
