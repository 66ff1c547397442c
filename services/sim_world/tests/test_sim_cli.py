"""The command lines: ``python -m sim_world`` and ``python -m sim_world.schema``.

Every mistake is one ``error:`` line and exit 2, never a traceback; a finished run
prints its summary."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import sim_world.schema
from rap_sdk.entry import run_cli
from sim_world.__main__ import cli
from sim_world.schema import render

TINY = """
room: {width: 4.0, height: 2.0}
robots:
  - name: r
    start: {x: 0.5, y: 1.0, theta: 0.0}
    route: [{x: 1.5, y: 1.0}]
"""


def run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=cwd,
        check=False,
    )


def one_error_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: "), stderr
    assert "Traceback" not in stderr
    return lines[0]


@pytest.fixture
def files(tmp_path: Path) -> Path:
    (tmp_path / "tiny.yaml").write_text(TINY, encoding="utf-8")
    (tmp_path / "binary.yaml").write_bytes(b"seed: 1\n\xff\xfe")
    (tmp_path / "impossible.yaml").write_text(
        TINY + "lidar: {range_min: 5.0, range_max: 2.0}\n", encoding="utf-8"
    )
    (tmp_path / "broken.yaml").write_text("robots: [\n", encoding="utf-8")
    return tmp_path


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--speed", "fast"], "Invalid value for '--speed'"),
        (["--speed", "0"], "--speed 0.0: the real-time factor must be a number > 0"),
        (["--speed", "nan"], "--speed nan:"),
        (["--duration", "-5"], "--duration -5.0: give seconds of sim time > 0"),
        (["--duration", "inf"], "--duration inf:"),
        (["--lockstep", "yes"], "unexpected extra argument"),
        (["--frobnicate"], "No such option: --frobnicate"),
        (["--world", "nope"], "'nope' is not a shipped world; the shipped worlds are corridor"),
        (["--world", "{dir}/missing.yaml"], "missing.yaml: no such world file; the shipped"),
        (["--world", "{dir}/binary.yaml"], "binary.yaml:2:1: the world file is not UTF-8 text"),
        (["--world", "{dir}/broken.yaml"], "broken.yaml:2:1: not valid YAML"),
        (["--world", "{dir}/impossible.yaml"], "impossible.yaml:7:20: lidar range_min 5 is"),
        (["--world", "{dir}"], ": is a directory"),
        (["--listen", "localhost:7447"], "--listen 'localhost:7447' is not a Zenoh endpoint"),
        (["--connect", "tcp"], "--connect 'tcp' is not a Zenoh endpoint"),
        (["--system", "a/b"], "--system: invalid system 'a/b'"),
        (["--system", "*"], "--system: invalid system '*'"),
        (["--log-level", "LOUD"], "--log-level 'LOUD' is not a logging level - use DEBUG"),
        (["--rerun", "{dir}"], "is a directory - give a file path"),
        (["--rerun", "{dir}/no/such/dir/x.rrd"], "does not exist - create it"),
    ],
)
def test_each_mistake_is_one_error_line_with_exit_2(
    args: list[str], words: str, files: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [a.format(dir=files) for a in args]
    with pytest.raises(SystemExit) as exc:
        run_cli(cli, argv, prog="python -m sim_world")
    assert exc.value.code == 2
    out = capsys.readouterr()
    assert words in one_error_line(out.err)
    assert out.out == ""  # nothing ran: no READY


def test_the_entry_point_itself_reports_a_mistake_in_one_line(tmp_path: Path) -> None:
    res = run("sim_world", "--speed", "-1", cwd=tmp_path)
    assert res.returncode == 2
    assert "--speed -1.0" in one_error_line(res.stderr)


@pytest.mark.zenoh
def test_an_endpoint_already_in_use_is_one_error_line(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        res = run("sim_world", "--listen", f"tcp/127.0.0.1:{port}", "--lockstep", cwd=tmp_path)
    assert res.returncode == 2
    line = one_error_line(res.stderr)
    assert "cannot open a Zenoh session" in line
    assert "check --listen and --connect" in line


@pytest.mark.zenoh
def test_a_finished_run_prints_its_summary(files: Path) -> None:
    res = run(
        "sim_world",
        "--world",
        str(files / "tiny.yaml"),
        "--lockstep",
        "--duration",
        "10",
        "--log-level",
        "WARNING",
        cwd=files,
    )
    assert res.returncode == 0, res.stderr
    ready, head, robot = res.stdout.splitlines()
    assert ready == "READY"
    assert head == "sim_world finished at 10 s of sim time (lockstep): 50 scans published"
    assert robot.startswith("  r: 0 collisions, 1 of 1 waypoints reached, route completed, ")
    assert robot.endswith(" m driven")


@pytest.mark.zenoh
def test_a_shipped_world_is_named(tmp_path: Path) -> None:
    res = run(
        "sim_world",
        "--world",
        "corridor",
        "--lockstep",
        "--duration",
        "1",
        "--log-level",
        "WARNING",
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    assert "5 scans published" in res.stdout
    assert "tb1: 0 collisions, 0 of 1 waypoints reached, route not completed" in res.stdout


def test_schema_help_writes_no_file(tmp_path: Path) -> None:
    res = run("sim_world.schema", "--help", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "Usage: python -m sim_world.schema" in res.stdout
    assert "world.schema.json" in res.stdout
    assert list(tmp_path.iterdir()) == []  # it used to write a file named --help


def test_schema_writes_the_given_path_or_the_default(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    res = run("sim_world.schema", "out.json", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "out.json").read_text(encoding="utf-8") == render()
    default = tmp_path / "default.json"
    monkeypatch.setattr(sim_world.schema, "SCHEMA_PATH", default)
    with pytest.raises(SystemExit) as exc:
        run_cli(sim_world.schema.cli, [], prog="python -m sim_world.schema")
    assert exc.value.code == 0
    assert json.loads(default.read_text(encoding="utf-8"))["title"] == "RAP sim_world world file"
    assert f"wrote {default}" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["{dir}"], "is a directory - give a file path"),
        (["{dir}/no/such/x.json"], "cannot write the schema"),
        (["a.json", "b.json"], "unexpected extra argument"),
        (["--bogus"], "No such option: --bogus"),
    ],
)
def test_schema_mistakes_are_one_error_line(
    args: list[str], words: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [a.format(dir=tmp_path) for a in args]
    with pytest.raises(SystemExit) as exc:
        run_cli(sim_world.schema.cli, argv, prog="python -m sim_world.schema")
    assert exc.value.code == 2
    assert words in one_error_line(capsys.readouterr().err)


@pytest.mark.zenoh
def test_metrics_count_the_scans_it_published(files: Path) -> None:
    from rap_sdk.fabric import free_port

    port = free_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sim_world",
            "--world",
            str(files / "tiny.yaml"),
            "--duration",
            "30",
            "--log-level",
            "WARNING",
            "--metrics",
            f"127.0.0.1:{port}",
        ],
        cwd=files,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "READY"
        import time
        import urllib.request

        sent = 0.0
        deadline = time.monotonic() + 20
        while sent < 3 and time.monotonic() < deadline:
            time.sleep(0.3)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
                text = r.read().decode()
            for line in text.splitlines():
                if line.startswith("rap_sent_total{") and 'component="sim_world"' in line:
                    sent = float(line.rsplit(" ", 1)[1])
        assert sent >= 3, text  # a scan and an odometry sample every 0.2 s of real time
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
