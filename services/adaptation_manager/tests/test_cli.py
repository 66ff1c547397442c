"""``python -m adaptation_manager``: one-line errors for bad options (exit 2), a running
manager that serves its dashboard and stops on SIGTERM (exit 0), and a second manager of
the same system refused (exit 1)."""

from __future__ import annotations

import re
import subprocess
import sys

import aiohttp
import anyio
import pytest
from rap_sdk.testing import Harness, OutputLines, free_port, stop_process

pytestmark = pytest.mark.anyio

MANAGER = [sys.executable, "-m", "adaptation_manager"]


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--system", "s", "--http", "nowhere"], "--http 'nowhere' is not HOST:PORT"),
        (["--system", "a/b"], "--system: invalid system"),
        (["--system", "s", "--connect", "nope"], "--connect 'nope' is not a Zenoh endpoint"),
        (["--system", "s", "--status-interval", "0"], "--status-interval 0: give a number"),
        (["--http", "127.0.0.1:0"], "Missing option '--system'"),
    ],
)
async def test_bad_options_exit_2_with_one_line(args: list[str], says: str) -> None:
    done = await anyio.run_process([*MANAGER, *args], check=False)
    err = done.stderr.decode()
    assert done.returncode == 2, err
    assert says in err
    assert err.count("\n") == 1, err
    assert err.startswith("error: ")


@pytest.mark.zenoh
async def test_it_serves_its_dashboard_refuses_a_second_one_and_stops_on_sigterm() -> None:
    async with Harness(system="cli", fabric="zenoh") as h:
        listen = f"tcp/127.0.0.1:{free_port()}"
        argv = [*MANAGER, "--system", "cli", "--connect", h.endpoint, "--http", "127.0.0.1:0"]
        argv += ["--listen", listen]
        async with await anyio.open_process(argv, stderr=subprocess.STDOUT) as proc:
            out = OutputLines(proc)
            async with anyio.create_task_group() as tg:
                tg.start_soon(out.pump)
                try:
                    _, m = await out.match(r"ready: system 'cli', dashboard (http://\S+/)")
                    async with aiohttp.ClientSession() as http, http.get(m[1] + "metrics") as res:
                        assert res.status == 200
                        assert "rap_manager_cycles_total 0.0" in await res.text()
                    # peers do not forward for each other: the second links to the first
                    again = [
                        *MANAGER,
                        "--system",
                        "cli",
                        "--connect",
                        listen,
                        "--http",
                        "127.0.0.1:0",
                    ]
                    with anyio.fail_after(20):
                        second = await anyio.run_process(again, check=False)
                    assert second.returncode == 1
                    assert re.search(
                        r"manager of system 'cli' is running already", second.stderr.decode()
                    )
                    proc.terminate()
                    with anyio.fail_after(10):
                        assert await proc.wait() == 0, str(out)
                finally:
                    await stop_process(proc)
