"""``python -m trust_checker`` as a user runs it (subprocesses)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import aiomqtt
import anyio
import pytest
from anyio.abc import Process
from anyio.streams.text import TextReceiveStream
from trust_checker.lang import load_spec
from trust_checker.tracefile import read_trace, run_trace

from services.trust_checker.tests.io_support import mosquitto

SPEC = """\
in x: Int
in y: Int
out z: Int
z = x + y
out d
d = x[-1, 0]
"""
TRACE = """\
0: x = 1
1: y = 2
2: x = 3
3: y = 4
"""
BAD = """\
in x: Int
out z: Int
z = x +
out w: Bool
w = y
"""


def run_cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "trust_checker", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )


def test_input_file_prints_what_run_trace_gives(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text(SPEC)
    (tmp_path / "t.trace").write_text(TRACE)
    res = run_cli(tmp_path / "s.dsrv", "--input-file", tmp_path / "t.trace")
    assert res.returncode == 0, res.stderr
    expected = run_trace(load_spec(SPEC), read_trace(TRACE))
    assert res.stdout.splitlines() == expected
    assert "z[1] = Int(3)" in expected


def test_bad_spec_exits_2_with_every_problem(tmp_path: Path) -> None:
    spec = tmp_path / "bad.dsrv"
    spec.write_text(BAD)
    (tmp_path / "t.trace").write_text(TRACE)
    res = run_cli(spec, "--input-file", tmp_path / "t.trace")
    assert res.returncode == 2
    assert res.stdout == ""
    assert f"{spec}:4:1:" in res.stderr
    assert "hint:" in res.stderr
    assert "not started" in res.stderr
    check = run_cli(spec, "--check")
    assert check.returncode == 2
    assert f"{spec}:4:1:" in check.stderr


def test_check_only_validates(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text(SPEC)
    res = run_cli(tmp_path / "s.dsrv", "--check")
    assert res.returncode == 0, res.stderr
    assert "ok (inputs: x, y; outputs: z, d)" in res.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((), "nothing to run on"),
        (("--mqtt", "host:notaport"), "is not HOST:PORT"),
        (("--mqtt", "h:1", "--topics", '{"x": {"topik": "a"}}'), "--topics"),
        (("--tick", "sometimes", "--mqtt", "h:1"), "unknown tick policy"),
        (("--fabric", "bad/system"), "invalid system"),
        (("--fabric", "s", "--connect", "nowhere"), "not a Zenoh endpoint"),
    ],
)
def test_bad_options_exit_2(tmp_path: Path, args: tuple[str, ...], message: str) -> None:
    (tmp_path / "s.dsrv").write_text(SPEC)
    res = run_cli(tmp_path / "s.dsrv", *args)
    assert res.returncode == 2
    assert message in res.stderr


def test_missing_spec_file_exits_2(tmp_path: Path) -> None:
    res = run_cli(tmp_path / "nope.dsrv", "--check")
    assert res.returncode == 2
    assert "cannot read spec" in res.stderr


async def _read_until(stream: TextReceiveStream, text: str, seen: list[str]) -> None:
    async for chunk in stream:
        seen.append(chunk)
        if text in "".join(seen):
            return
    raise AssertionError(f"{text!r} never came:\n{''.join(seen)}")


async def _stop(proc: Process) -> int:
    proc.send_signal(signal.SIGTERM)
    with anyio.fail_after(10):
        return await proc.wait()


@pytest.mark.anyio
async def test_mqtt_mode_runs_until_sigterm_and_exits_0(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text(SPEC)
    async with mosquitto(tmp_path) as broker:
        proc = await anyio.open_process(
            [
                sys.executable,
                "-m",
                "trust_checker",
                str(tmp_path / "s.dsrv"),
                "--mqtt",
                f"127.0.0.1:{broker.port}",
                "--tagged",
                "--topics",
                '{"x": {"topic": "in/x"}}',
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        async with proc, aiomqtt.Client("127.0.0.1", broker.port, timeout=5) as client:
            assert proc.stdout is not None
            assert proc.stderr is not None
            err: list[str] = []
            out: list[str] = []
            try:
                with anyio.fail_after(20):
                    await _read_until(TextReceiveStream(proc.stderr), "ready:", err)
                    await client.subscribe("z")
                    await client.publish("in/x", "1")
                    await client.publish("y", '{"value": 2}')
                    async for message in client.messages:
                        assert json.loads(bytes(message.payload)) == {"Int": 3}
                        break
                    await _read_until(TextReceiveStream(proc.stdout), "z[1] = Int(3)", out)
            finally:
                code = await _stop(proc)
        assert code == 0, "".join(err)
        assert "d[0] = Int(0)" in "".join(out)


@pytest.mark.anyio
@pytest.mark.zenoh
async def test_fabric_mode_runs_until_sigint_and_exits_0(tmp_path: Path) -> None:
    from rap_schemas import Empty, TrustOutput, keys
    from rap_sdk import Sealer, ZenohConfig, ZenohFabric
    from rap_sdk.envelope import typed_decoder
    from rap_sdk.fabric import free_port

    (tmp_path / "s.dsrv").write_text("in ev_go\nout n: Int\nn = 1 + default(n[1], 0)\n")
    port = free_port()
    proc = await anyio.open_process(
        [
            sys.executable,
            "-m",
            "trust_checker",
            str(tmp_path / "s.dsrv"),
            "--fabric",
            "clisys",
            "--listen",
            f"tcp/127.0.0.1:{port}",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    config = ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"])
    async with proc:
        assert proc.stderr is not None
        err: list[str] = []
        try:
            with anyio.fail_after(20):
                await _read_until(TextReceiveStream(proc.stderr), "ready:", err)
                async with ZenohFabric(config) as fab:
                    sub = fab.subscribe(keys.pattern("clisys", keys.Kind.TRUST))
                    with sub:
                        key = keys.event("clisys", "go")
                        await fab.wait_matched(key)
                        await fab.wait_matched(keys.trust("clisys", "n"))
                        payload, _ = Sealer("t").seal_message(key, Empty())
                        await fab.publish(key, payload)
                        sample = await sub.get()
        finally:
            proc.send_signal(signal.SIGINT)
            with anyio.fail_after(10):
                code = await proc.wait()
    assert code == 0, "".join(err)
    out = typed_decoder(TrustOutput)(sample.payload).body
    assert (out.stream, out.tick, out.value) == ("n", 0, 1)
