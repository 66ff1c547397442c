"""``python -m trust_checker`` with credentials, as an operator runs it (subprocesses): a
checker on a TLS broker with a password file and identities, and ``--send-swap`` sending
it a spec unsigned (refused) and signed by an operator (taken), over MQTT and over the
fabric. The passwords never go on a command line."""

from __future__ import annotations

import os
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
from rap_sdk.fabric import free_port

from libs.rap_sdk.tests.certs_support import make_certs
from services.trust_checker.tests.io_support import BrokerTls, mosquitto

SPEC = 'in stage: Str\nin phase: Str\nout started: Bool\nstarted = phase == "start"\n'
NEW = "in stage: Str\nout stage_order_ok: Bool\nstage_order_ok = true\n"
PASSWORDS = {"checker": "pw-of-the-checker", "alice": "pw-of-alice"}


def run_cli(
    *args: str | Path, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "trust_checker", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env={**_clean_env(), **(env or {})},
    )


def _clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("RAP_CERTS", "RAP_AS")}


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    base = tmp_path_factory.mktemp("pki")
    mqtt = make_certs(
        base / "mqtt",
        {"broker": "", "checker": "", "alice": ""},
        system="mqtt",
        hosts={"broker": ["127.0.0.1"]},
    )
    rap = make_certs(base / "rap", {"alice": "operator", "edge.runner": "process"})
    return mqtt, rap


def test_credential_mistakes_are_one_error_line(tmp_path: Path) -> None:
    (tmp_path / "s.dsrv").write_text(SPEC)
    spec = tmp_path / "s.dsrv"
    cases = [
        (
            ("--mqtt", "127.0.0.1:1", "--mqtt-user", "u", "--mqtt-password-env", "TC_NOPE"),
            "error: MQTT password: $TC_NOPE is not set - export it",
        ),
        (
            ("--mqtt", "127.0.0.1:1", "--mqtt-password-file", "pw"),
            "error: an MQTT password needs a user name (--mqtt-user) too",
        ),
        (("--fabric", "demo", "--mqtt-ca", "ca.pem"), "error: the --mqtt-* options go with --mqtt"),
        (
            ("--fabric", "demo", "--certs", str(tmp_path / "none")),
            "error: --certs: " + str(tmp_path / "none" / "ca.pem") + ": no such file",
        ),
        (
            (
                *("--send-swap", "--fabric", "demo", "--connect", "tcp/127.0.0.1:1"),
                *("--as", "alice", "--certs", str(tmp_path)),
            ),
            "error: --as alice: " + str(tmp_path / "alice.pem") + ": no such file",
        ),
        (("--send-swap", "--input-file", "t"), "error: --send-swap sends SPEC to a running"),
        (("--send-swap", "--fabric", "demo"), "error: --send-swap --fabric: give --connect"),
    ]
    for args, message in cases:
        res = run_cli(spec, *args)
        assert res.returncode == 2, (args, res.stderr)
        assert message in res.stderr, (args, res.stderr)
        assert "Traceback" not in res.stderr
    # there is no option that takes the password itself
    res = run_cli(spec, "--mqtt", "127.0.0.1:1", "--mqtt-password", "secret")
    assert res.returncode == 2
    assert "No such option" in res.stderr


async def _read_until(stream: TextReceiveStream, text: str, seen: list[str]) -> None:
    async for chunk in stream:
        seen.append(chunk)
        if text in "".join(seen):
            return
    raise AssertionError(f"{text!r} never came:\n{''.join(seen)}")


@asynccontextmanager
async def checker(args: list[str], env: dict[str, str]) -> AsyncIterator[list[str]]:
    """A checker process, ready; the list yielded holds its stderr (all of it once the
    block is left and the process has ended)."""
    proc: Process = await anyio.open_process(
        [sys.executable, "-m", "trust_checker", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env={**_clean_env(), **env},
    )
    err: list[str] = []
    async with proc:
        assert proc.stderr is not None
        try:
            with anyio.fail_after(20):
                await _read_until(TextReceiveStream(proc.stderr), "ready:", err)
            yield err
        finally:
            proc.send_signal(signal.SIGTERM)
            with anyio.fail_after(10):
                err.extend([c async for c in TextReceiveStream(proc.stderr)])  # to its end
                code = await proc.wait()
            assert code == 0, "".join(err)


async def _send(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return await anyio.to_thread.run_sync(lambda: run_cli(*args, env=env))


@pytest.mark.anyio
async def test_send_swap_over_a_locked_down_broker(tmp_path: Path, pki: tuple[Path, Path]) -> None:
    mqtt, rap = pki
    spec, new = tmp_path / "s.dsrv", tmp_path / "new.dsrv"
    spec.write_text(SPEC)
    new.write_text(NEW)
    pw_file = tmp_path / "checker.pw"
    pw_file.write_text(PASSWORDS["checker"] + "\n")
    pw_file.chmod(0o600)
    tls = BrokerTls(mqtt / "ca.pem", mqtt / "broker.pem", mqtt / "broker.key")
    async with mosquitto(tmp_path, passwords=PASSWORDS, tls=tls) as broker:
        where = [
            "--mqtt",
            f"127.0.0.1:{broker.port}",
            "--node",
            "tc",
            "--mqtt-ca",
            str(mqtt / "ca.pem"),
        ]
        run = [
            str(spec),
            *where,
            "--mqtt-user",
            "checker",
            "--mqtt-password-file",
            str(pw_file),
            "--mqtt-cert",
            str(mqtt / "checker.pem"),
            "--mqtt-key",
            str(mqtt / "checker.key"),
        ]
        operator = [
            str(new),
            "--send-swap",
            *where,
            "--mqtt-user",
            "alice",
            "--mqtt-password-env",
            "ALICE_MQTT_PW",
            "--mqtt-cert",
            str(mqtt / "alice.pem"),
            "--mqtt-key",
            str(mqtt / "alice.key"),
        ]
        env = {"ALICE_MQTT_PW": PASSWORDS["alice"], "RAP_CERTS": str(rap)}
        async with checker(run, {"RAP_CERTS": str(rap)}) as err:
            assert "over TLS as checker" in "".join(err)
            unsigned = await _send(operator, env)
            assert unsigned.returncode == 1, unsigned.stderr
            assert "swap refused: unsigned request" in unsigned.stderr
            assert "error: tc: the swap was refused; the running spec stays" in unsigned.stderr
            process = await _send([*operator, "--as", "edge.runner"], env)
            assert process.returncode == 1
            assert "'edge.runner' (role process) may not swap the spec of tc" in process.stderr
            signed = await _send([*operator, "--as", "alice"], env)
            assert signed.returncode == 0, signed.stderr
            assert signed.stdout.startswith("tc: swapped to new.dsrv at tick 0: inputs stage;")
    for res in (unsigned, process, signed):
        assert PASSWORDS["alice"] not in res.stdout + res.stderr


@pytest.mark.anyio
@pytest.mark.zenoh
async def test_send_swap_over_the_fabric(tmp_path: Path, pki: tuple[Path, Path]) -> None:
    _, rap = pki
    spec, new = tmp_path / "s.dsrv", tmp_path / "new.dsrv"
    spec.write_text(SPEC)
    new.write_text(NEW)
    port = free_port()
    run = [str(spec), "--fabric", "clisec", "--node", "tc", "--listen", f"tcp/127.0.0.1:{port}"]
    send = [str(new), "--send-swap", "--fabric", "clisec", "--node", "tc"]
    send += ["--connect", f"tcp/127.0.0.1:{port}", "--certs", str(rap)]
    async with checker([*run, "--certs", str(rap)], {}) as err:
        unsigned = await _send(send, {})
        assert unsigned.returncode == 1, unsigned.stderr
        assert "swap refused: unsigned request" in unsigned.stderr
        signed = await _send([*send, "--as", "alice"], {})
        assert signed.returncode == 0, signed.stderr
        assert signed.stdout.startswith("tc: swapped to new.dsrv at tick 0")
    log = "".join(err)
    assert '"who":"unauthenticated"' in log
    assert '"result":"refused"' in log
