"""``python -m knowledge``: every mistake is one 'error:' line and exit code 2, never a
traceback; the memory backend says at start-up and in --help that it keeps nothing."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from rap_sdk.testing import free_port


def run(*args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "knowledge", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--system", "a b"], "--system: invalid system 'a b'"),
        (["--backend", "nope"], "Invalid value for '--backend'"),
        (["--history-max", "0"], "--history-max 0: keep at least 1"),
        (["--listen", "tcpxx"], "--listen 'tcpxx' is not a Zenoh endpoint"),
        (["--log-level", "LOUD"], "'LOUD' is not a logging level"),
        (["--config", "/nonexistent/kb.yaml"], "cannot read the knowledge config"),
        (["--bogus"], "No such option: --bogus"),
        (
            ["--backend", "redis", "--redis-url", f"redis://127.0.0.1:{free_port()}/0"],
            "unreachable",
        ),
        (
            ["--backend", "memcached", "--memcached-url", f"memcached://127.0.0.1:{free_port()}"],
            "apt-get install memcached",
        ),
        (["--backend", "memcached", "--memcached-url", "redis://x"], "write memcached://HOST"),
        (["--backend", "kafka", "--kafka-url", "redis://x"], "write kafka://HOST"),
        (["--backend", "kafka", "--kafka-topic", "a/b"], "Kafka topic 'a/b'"),
        (
            ["--model-grants", '{"edge.runner": {"m": "all"}}'],
            "--model-grants: Invalid enum value 'all'",
        ),
        (["--model-grants", "edge.runner=m"], "give JSON such as"),
    ],
)
def test_mistakes_are_one_line_and_exit_2(args: list[str], says: str) -> None:
    done = run(*args)
    assert done.returncode == 2, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, done.stderr
    assert says in errors[0]
    assert "Traceback" not in done.stderr


def test_bad_files_are_located(tmp_path: Path) -> None:
    bad = tmp_path / "kb.yaml"
    bad.write_text("system: t\nbackend: memry\n")
    done = run("--config", str(bad))
    assert done.returncode == 2
    assert f"error: {bad}:2:10: Invalid enum value 'memry'" in done.stderr
    binary = tmp_path / "kb.bin"
    binary.write_bytes(b"\x89PNG\x00")
    done = run("--config", str(binary))
    assert f"error: {binary}:1:1: the knowledge config is not UTF-8 text" in done.stderr
    done = run("--backend", "sqlite", "--sqlite-path", str(binary))
    assert "error: sqlite store" in done.stderr
    assert "file is not a database" in done.stderr


def test_the_memory_backend_says_it_keeps_nothing() -> None:
    assert "lost on restart" in " ".join(run("--help").stdout.split())
    taken = free_port()
    with subprocess.Popen(
        [sys.executable, "-m", "knowledge", "--listen", f"tcp/127.0.0.1:{taken}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    ) as proc:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "READY"
        proc.terminate()
        _, err = proc.communicate(timeout=20)
    assert "knowledge backend 'memory': every write, acknowledged or not, is lost" in err
    assert "listening on tcp/127.0.0.1:" in err
