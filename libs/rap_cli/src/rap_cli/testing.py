"""Test helpers for whole systems run as a user runs them: ``rap up --all`` of a model,
as a child process, until the block ends (then ``rap down``, which must stop it all).

    copy = model_copy(LIDAR_MODEL, tmp_path)          # the edge's port made free
    async with rap_up(copy, tmp_path / "run") as out:  # both compute nodes are up
        await out.line("anomaly")
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from pathlib import Path

import anyio
from rap_sdk.fabric import free_port
from rap_sdk.testing import OutputLines, stop_process

__all__ = ["EDGE_ENDPOINT", "model_copy", "rap_command", "rap_up"]

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
