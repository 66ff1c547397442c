"""kill -9 of the knowledge service with the sqlite backend loses no acknowledged write."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import anyio
import pytest
from anyio.abc import Process
from anyio.streams.text import TextReceiveStream
from rap_schemas import keys
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.knowledge import KnowledgeClient
from rap_sdk.testing import free_port

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh]


@asynccontextmanager
async def service_process(db: Path, port: int) -> AsyncIterator[Process]:
    proc = await anyio.open_process(
        [
            sys.executable,
            "-m",
            "knowledge",
            "--system",
            "t",
            "--backend",
            "sqlite",
            "--sqlite-path",
            str(db),
            "--listen",
            f"tcp/127.0.0.1:{port}",
            "--log-level",
            "WARNING",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    assert proc.stdout is not None
    seen = ""
    with anyio.fail_after(20):
        async for chunk in TextReceiveStream(proc.stdout):
            seen += chunk
            if "READY" in seen:
                break
    try:
        yield proc
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        await proc.aclose()


async def test_acknowledged_writes_survive_kill_9(tmp_path: Path) -> None:
    db, port = tmp_path / "kb.sqlite3", free_port()
    acked: dict[str, int] = {}
    async with ZenohFabric(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"])) as fabric:
        async with service_process(db, port) as proc:
            await fabric.wait_matched(keys.kb("t", "_keys"), queryable=True, timeout=20)
            async with KnowledgeClient(fabric=fabric, system="t", writer="w", timeout=5) as kb:
                for i in range(200):
                    acked[f"k/{i % 20}"] = await kb.write(f"k/{i % 20}", i, durable=True)
            proc.send_signal(signal.SIGKILL)  # no shutdown, no flush
            await proc.wait()
        async with service_process(db, port):
            await fabric.wait_matched(keys.kb("t", "_keys"), queryable=True, timeout=20)
            async with KnowledgeClient(fabric=fabric, system="t", writer="r", timeout=5) as kb:
                assert len(await kb.keys("k/*")) == 20
                for key, version in acked.items():
                    rec = await kb.read_record(key)
                    assert rec is not None
                    assert rec.version == version
                    assert await kb.read(key, int) == max(
                        i for i in range(200) if f"k/{i % 20}" == key
                    )
                assert len(await kb.history("k/0")) == 10
