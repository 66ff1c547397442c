"""``python -m rap_cli.router``: a bad config exits 2 with one line; two routers link,
and a cut link is logged as lost and, once it heals, as restored."""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import anyio
import pytest
from rap_sdk.fabric import free_port
from rap_sdk.testing import OutputLines

pytestmark = pytest.mark.anyio

TIMEOUT = 20.0


def _config(path: Path, listen: str, connect: list[str]) -> Path:
    conf = {
        "mode": "router",
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        # a short lease: a stopped router is noticed within a second
        "transport": {"link": {"tx": {"lease": 1000, "keep_alive": 4}}},
        "listen": {"endpoints": [listen]},
        "connect": {
            "endpoints": connect,
            "timeout_ms": -1,
            "exit_on_failure": False,
            "retry": {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2},
        },
    }
    path.write_text("// a test router\n" + json.dumps(conf, indent=2), encoding="utf-8")
    return path


@contextlib.asynccontextmanager
async def router(config: Path) -> AsyncIterator[OutputLines]:
    proc = await anyio.open_process(
        [sys.executable, "-m", "rap_cli.router", "--config", str(config)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    r = OutputLines(proc, timeout=TIMEOUT)
    try:
        async with anyio.create_task_group() as tg:
            tg.start_soon(r.pump)
            try:
                yield r
            finally:
                with anyio.CancelScope(shield=True):
                    if proc.returncode is None:
                        proc.send_signal(signal.SIGCONT)
                        proc.terminate()
                        with anyio.fail_after(TIMEOUT):
                            await proc.wait()
                tg.cancel_scope.cancel()
    finally:
        await proc.aclose()


@pytest.mark.zenoh
async def test_a_cut_link_is_logged_lost_and_restored(tmp_path: Path) -> None:
    pa, pb = free_port(), free_port()
    a_conf = _config(tmp_path / "a.json5", f"tcp/127.0.0.1:{pa}", [])
    b_conf = _config(tmp_path / "b.json5", f"tcp/127.0.0.1:{pb}", [f"tcp/127.0.0.1:{pa}"])
    async with router(a_conf) as a:
        _, m = await a.match(rf"router (\w+) listening on tcp/127\.0\.0\.1:{pa}")
        a_zid = m[1]
        async with router(b_conf) as b:
            _, m = await b.match(rf"router (\w+) listening on .*; connecting to tcp/127.0.0.1:{pa}")
            b_zid = m[1]
            up, _ = await a.match(rf"link to {b_zid} up \(router; 1 link\(s\) up\)")
            await b.match(rf"link to {a_zid} up \(router")
            b.proc.send_signal(signal.SIGSTOP)  # b hangs: a's lease on the link runs out
            lost, _ = await a.match(rf"link to {b_zid} lost \(router; 0 link\(s\) left\)", after=up)
            assert "WARNING" in a.lines[lost]
            b.proc.send_signal(signal.SIGCONT)
            await a.match(rf"link to {b_zid} restored \(router; 1 link\(s\) up\)", after=lost)
            b.proc.terminate()
            with anyio.fail_after(TIMEOUT):
                assert await b.proc.wait() == 0, "\n".join(b.lines)
            await b.line("router stopped")
        await a.match(rf"link to {b_zid} lost", after=lost + 1)
        a.proc.send_signal(signal.SIGINT)
        with anyio.fail_after(TIMEOUT):
            assert await a.proc.wait() == 0, "\n".join(a.lines)
        await a.line("received SIGINT; stopping")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (None, "no such file"),
        ("{mode: 'router', listen: {endpoints: [", "not a usable Zenoh config"),
        ('{"mode": "client"}', "mode is 'client' - a router config says mode: 'router'"),
        ('{"listen": {"endpoints": "tcp/127.0.0.1:1"}}', "not a usable Zenoh config"),
    ],
    ids=["missing", "not-json5", "client-mode", "not-a-list"],
)
async def test_a_bad_config_exits_2_with_one_line(
    tmp_path: Path, text: str | None, message: str
) -> None:
    path = tmp_path / "router.json5"
    if text is not None:
        path.write_text(text, encoding="utf-8")
    with anyio.fail_after(TIMEOUT):
        result = await anyio.run_process(
            [sys.executable, "-m", "rap_cli.router", "--config", str(path)], check=False
        )
    err = result.stderr.decode()
    assert result.returncode == 2, err
    assert err.startswith(f"error: {path}: {message}"), err
    assert err.count("\n") == 1, err
    assert " at /" not in err  # no Rust source locations


@pytest.mark.zenoh
async def test_an_endpoint_taken_exits_1(tmp_path: Path) -> None:
    port = free_port()
    conf = _config(tmp_path / "a.json5", f"tcp/127.0.0.1:{port}", [])
    async with router(conf) as first:
        await first.line("listening on")
        with anyio.fail_after(TIMEOUT):
            result = await anyio.run_process(
                [sys.executable, "-m", "rap_cli.router", "--config", str(conf)], check=False
            )
    err = result.stderr.decode()
    assert result.returncode == 1, err
    assert f"error: {conf}: the router cannot open its Zenoh session" in err
    assert "Address already in use" in err
    assert err.count("\n") == 1, err
