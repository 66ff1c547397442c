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
from rap_sdk import entry
from trust_checker.__main__ import cli
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


def run_cli(*args: str | Path, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "trust_checker", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
        cwd=cwd,
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
    assert "Traceback" not in res.stderr
    assert res.stderr.splitlines()[-1].startswith(f"error: {spec}: 1 problem; not started - ")
    check = run_cli(spec, "--check")
    assert check.returncode == 2
    assert f"{spec}:4:1:" in check.stderr


def test_check_only_validates(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text(SPEC)
    res = run_cli(tmp_path / "s.dsrv", "--check")
    assert res.returncode == 0, res.stderr
    assert "ok (inputs: x, y; outputs: z, d)" in res.stdout


def one_error_line(stderr: str) -> str:
    """The single ``error: what - how to fix`` line a mistake gives (never a traceback)."""
    assert "Traceback" not in stderr, stderr
    lines = stderr.splitlines()
    assert len(lines) == 1, stderr
    (line,) = lines
    assert line.startswith("error: "), line
    # how to fix it: after " - ", or the key checks' "...: use <what a name may be>"
    assert " - " in line or ": use " in line, f"no 'how to fix' part: {line}"
    return line


MISTAKES = [
    (("--tick", "sometimes", "--mqtt", "h:1"), "--tick: unknown tick policy 'sometimes'"),
    (("--tick", "window:0ms", "--mqtt", "h:1"), "--tick: duration '0ms' is out of range"),
    (("--mqtt", "host:notaport"), "--mqtt 'host:notaport' is not HOST:PORT"),
    (("--mqtt", "h:70000"), "--mqtt 'h:70000' is not HOST:PORT"),
    (("--mqtt", "h:1", "--topics", '{"x": {"topik": "a"}}'), "--topics: Object contains unknown"),
    (("--mqtt", "h:1", "--topics", "not json"), "--topics is not a JSON object"),
    (("--mqtt", "h:1", "--topics", "[" * 5000), "--topics: Expected `object`, got `array`"),
    (("--fabric", "s", "--fabric-inputs", "[1]"), "--fabric-inputs: Expected `object`"),
    (("--fabric", "s", "--no-default-inputs"), "--no-default-inputs leaves nothing to read"),
    (("--fabric", "bad/system"), "--fabric: invalid system"),
    (("--fabric", "s", "--node", "a/b"), "--node 'a/b'"),
    (("--fabric", "s", "--connect", "nowhere"), "--connect 'nowhere' is not a Zenoh endpoint"),
    (("--fabric", "s", "--listen", "tcp"), "--listen 'tcp' is not a Zenoh endpoint"),
    (("--log-level", "LOUD"), "--log-level 'LOUD' is not a logging level"),
    (("--bogus",), "No such option: --bogus"),
    ((), "nothing to run on"),
    (("--input-file", "t.trace", "--mqtt", "h:1"), "--input-file runs alone"),
    (("--input-file", "t.trace", "--redis", "redis://h"), "--input-file runs alone"),
    (("--redis", "http://h:1"), "'http://h:1' is not a Redis URL (--redis)"),
    (("--redis", "redis://:pw@h"), "the Redis URL (--redis) holds a user name or a password"),
    (("--redis", "redis://h:1/x"), "'x' is not a database number"),
    (("--redis", "redis://h", "--redis-channels", "[1]"), "--redis-channels: Expected `object`"),
    (("--redis", "redis://h", "--redis-cert", "c.pem"), "needs its key and the key its cert"),
    (("--fabric", "s", "--redis-user", "u"), "the --redis-* options go with --redis URL"),
    (("--redis", "redis://h", "--redis-password-env", "TC_NOPE_X"), "$TC_NOPE_X is not set"),
]


@pytest.mark.parametrize(("args", "message"), MISTAKES, ids=[m for _, m in MISTAKES])
def test_every_mistake_is_one_error_line_and_exit_2(
    tmp_path: Path,
    args: tuple[str, ...],
    message: str,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    (tmp_path / "s.dsrv").write_text(SPEC)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exited:
        entry.run_cli(cli, ["s.dsrv", *args], prog="python -m trust_checker")
    assert exited.value.code == 2
    line = one_error_line(capsys.readouterr().err)
    assert message in line


def test_mistakes_in_files_are_one_located_line(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text(SPEC)
    (tmp_path / "bin.dsrv").write_bytes(b"in x: Int\nout y\ny = \xff\xfex\n")
    (tmp_path / "bin.trace").write_bytes(b"0: x = 1\n1: x = \x00\x9f\n")
    (tmp_path / "bad.trace").write_text("0: x = 1\n1: x = 2 +\n")
    cases = [
        (("nope.dsrv", "--check"), "nope.dsrv: cannot read the spec: No such file"),
        (("bin.dsrv", "--check"), "bin.dsrv:3:5: the spec is not UTF-8 text (byte 0xff)"),
        ((".", "--check"), ".: is a directory"),
        (("s.dsrv", "--input-file", "nope.trace"), "nope.trace: cannot read the trace"),
        (
            ("s.dsrv", "--input-file", "bin.trace"),
            "bin.trace:2:9: the trace is not UTF-8 text (byte 0x9f)",
        ),
        (("s.dsrv", "--input-file", "bad.trace"), "bad.trace:2:"),
    ]
    for args, message in cases:
        res = run_cli(*args, cwd=tmp_path)
        assert res.returncode == 2, (args, res.stderr)
        assert res.stdout == ""
        assert message in one_error_line(res.stderr), args


def test_a_run_time_error_in_a_trace_comes_after_every_tick_before_it(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text("in x: Int\nout y: Int\ny = 10 / x\nout n: Int\nn = 1\n")
    (tmp_path / "t.trace").write_text("0: x = 5\n1: x = 2\n// zero next\n2: x = 0\n3: x = 1\n")
    for extra in ((), ("--explain",)):
        res = run_cli("s.dsrv", "--input-file", "t.trace", *extra, cwd=tmp_path)
        assert res.returncode == 1, res.stderr
        assert res.stdout.splitlines() == [
            "y[0] = Int(2)",
            "n[0] = Int(1)",
            "y[1] = Int(5)",
            "n[1] = Int(1)",
        ]
        line = one_error_line(res.stderr)
        assert line.startswith("error: t.trace:4:1: Int division by zero: 10 / 0 (guard")
        assert "in 'y' at tick 2 (s.dsrv:3:8) - " in line


def test_a_refused_value_in_a_trace_comes_after_every_tick_before_it(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text(SPEC)
    (tmp_path / "t.trace").write_text("0: x = 1\n   y = 2\n1: x = 3\n2: y = true\n")
    res = run_cli("s.dsrv", "--input-file", "t.trace", cwd=tmp_path)
    assert res.returncode == 2
    assert res.stdout.splitlines() == [
        "z[0] = Int(3)",
        "d[0] = Int(0)",
        "z[1] = Int(5)",
        "d[1] = Int(1)",
    ]
    line = one_error_line(res.stderr)
    assert line.startswith("error: t.trace:4:1: input 'y' at tick 2: expected Int, got Bool")


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
