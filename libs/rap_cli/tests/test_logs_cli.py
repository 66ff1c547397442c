"""``rap logs`` reads each source: the JSON lines files of a run dir (rotated ones
included, in time order, filtered), a Redis stream (a redis-server of the test's own),
and, with ``-f``, the fabric live (log lines and rejections, told apart by type)."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import anyio
import pytest
from rap_schemas import Rejection, keys
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.envelope import Sealer
from rap_sdk.logs import FabricLogHandler, LogContext, RedisStreamHandler, add_file_log
from rap_sdk.testing import OutputLines, free_port, require_binary, stop_process

SYSTEM = "logdemo"
RAP = str(Path(sys.executable).with_name("rap"))


@pytest.fixture
def logger(request: pytest.FixtureRequest) -> Iterator[logging.Logger]:
    lg = logging.getLogger(f"test_logs_cli.{request.node.name}")
    lg.setLevel(logging.DEBUG)
    lg.propagate = False
    yield lg
    for h in list(lg.handlers):
        lg.removeHandler(h)


def _rap(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [RAP, "logs", *args], capture_output=True, text=True, timeout=60, check=False
    )


def _write_run_dir(run: Path, logger: logging.Logger) -> None:
    """What rap up's services leave: a runner on robot (its file rotated once) and
    knowledge on edge, written by the real file handler."""
    analysis = logger.getChild("app.analysis")  # a component's module logs
    runner_ctx = LogContext(
        system=SYSTEM,
        compute_node="robot",
        process="runner",
        components={analysis.name: "analysis"},
    )
    kb_ctx = LogContext(system=SYSTEM, compute_node="edge", process="knowledge")
    runner = add_file_log(
        run / "robot" / "logs" / "runner.jsonl", runner_ctx, max_bytes=600, logger=logger
    )
    try:
        logger.info("runner starts")
        for i in range(3):
            analysis.warning("anomaly %d found", i)
    finally:
        runner.close()
    time.sleep(0.002)  # the knowledge lines come later
    kb = add_file_log(run / "edge" / "logs" / "knowledge.jsonl", kb_ctx, logger=logger)
    try:
        try:
            raise OSError("disk full")
        except OSError:
            logger.exception("store failed")
    finally:
        kb.close()
    with (run / "edge" / "logs" / "knowledge.jsonl").open("a") as f:
        f.write("this is not a record\n")


def test_the_history_from_the_files_of_a_run_dir(tmp_path: Path, logger: logging.Logger) -> None:
    run = tmp_path / "run"
    _write_run_dir(run, logger)
    assert (run / "robot" / "logs" / "runner.jsonl.1").exists()  # it did rotate
    res = _rap("--run-dir", str(run))
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    msgs = [line for line in lines if not line.startswith("    ")]
    assert len(msgs) == 5, res.stdout
    assert "INFO     runner@robot" in msgs[0]
    assert msgs[0].endswith(": runner starts")
    assert "WARNING  analysis/runner@robot" in msgs[1]
    assert msgs[1].endswith("anomaly 0 found")
    assert msgs[3].endswith("anomaly 2 found")  # the rotated file first: time order
    assert "ERROR    knowledge@edge" in msgs[4]
    assert "    OSError: disk full" in lines  # the traceback, indented below
    assert "1 line(s) of" in res.stderr  # the line that is not a record
    # a component, a level, JSON
    res = _rap("analysis", "--run-dir", str(run), "--json")
    assert res.returncode == 0, res.stderr
    objs = [json.loads(line) for line in res.stdout.splitlines()]
    assert [o["message"] for o in objs] == [f"anomaly {i} found" for i in range(3)]
    assert {o["component"] for o in objs} == {"analysis"}
    res = _rap("--run-dir", str(run), "--level", "error", "--json")
    assert [json.loads(x)["process"] for x in res.stdout.splitlines()] == ["knowledge"]
    # --since: nothing is older than a day, everything is older than now
    assert len(_rap("--run-dir", str(run), "--since", "1d").stdout.splitlines()) == len(lines)
    res = _rap("--run-dir", str(run), "--since", "0s")
    assert res.returncode == 0
    assert res.stdout == ""


def test_usage_errors_say_what_to_do(tmp_path: Path) -> None:
    cases = [
        (["--level", "loud", "--run-dir", str(tmp_path)], "is not a level"),
        (["--since", "ten minutes", "--run-dir", str(tmp_path)], "is not a duration"),
        (["-f", "--since", "10m", "-s", SYSTEM], "drop one"),
        (["-n", "3", "--run-dir", str(tmp_path)], "-n COUNT goes with -f"),
        (["--redis", "redis://127.0.0.1:1/0"], "which system?"),
    ]
    for args, said in cases:
        res = subprocess.run(
            [RAP, "logs", *args],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
            cwd=tmp_path,
            env={"PATH": "/usr/bin:/bin"},
        )
        assert res.returncode == 2, (args, res.stdout, res.stderr)
        assert "rap: error: " in res.stderr
        assert said in res.stderr, (args, res.stderr)
    res = _rap("--run-dir", str(tmp_path))  # nothing there
    assert res.returncode == 1
    assert "no JSON lines logs under" in res.stderr


@pytest.mark.anyio
@pytest.mark.redis
async def test_the_history_from_a_redis_stream(tmp_path: Path, logger: logging.Logger) -> None:
    binary = require_binary("redis-server", hint="apt-get install redis-server")
    port = free_port()
    argv = [binary, "--bind", "127.0.0.1", "--port", str(port), "--dir", str(tmp_path)]
    argv += ["--save", "", "--appendonly", "no"]
    url = f"redis://127.0.0.1:{port}/0"
    async with await anyio.open_process(argv, stdout=subprocess.PIPE) as server:
        try:
            out = OutputLines(server, timeout=10)
            async with anyio.create_task_group() as tg:
                tg.start_soon(out.pump)
                await out.line("Ready to accept connections")
                ctx = LogContext(system=SYSTEM, process="knowledge")
                handler = RedisStreamHandler(url, stream=f"rap:{SYSTEM}:log", context=ctx)
                logger.addHandler(handler)
                await tg.start(handler.run)
                logger.info("stored %d records", 3)
                logger.error("lost the store")
                with anyio.fail_after(10):
                    while handler.stats.sent < 2:  # noqa: ASYNC110 (a counter)
                        await anyio.sleep(0.02)
                await handler.aclose()
                done = await anyio.run_process(
                    [RAP, "logs", "--redis", url, "-s", SYSTEM], check=False
                )
                err = await anyio.run_process(
                    [RAP, "logs", "--redis", f"redis://127.0.0.1:{free_port()}/0", "-s", SYSTEM],
                    check=False,
                )
                tg.cancel_scope.cancel()
        finally:
            await stop_process(server, grace=5)
    assert done.returncode == 0, done.stderr.decode()
    text = done.stdout.decode().splitlines()
    assert len(text) == 2
    assert text[0].endswith("stored 3 records")
    assert "ERROR    knowledge" in text[1]
    assert err.returncode == 1
    assert b"cannot read the log stream" in err.stderr


@pytest.mark.anyio
@pytest.mark.zenoh
async def test_follow_shows_log_lines_and_rejections_from_the_fabric(
    logger: logging.Logger,
) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    client = ZenohConfig(mode="client", listen=[], connect=[ep])
    argv = [RAP, "logs", "-f", "-c", ep, "-s", SYSTEM, "-n", "3"]
    async with (
        ZenohFabric(ZenohConfig(mode="router", listen=[ep])),
        ZenohFabric(client) as fabric,
        anyio.create_task_group() as tg,
    ):
        ctx = LogContext(system=SYSTEM, compute_node="robot", process="runner")
        handler = FabricLogHandler(fabric, system=SYSTEM, node="runner-robot", context=ctx)
        logger.addHandler(handler)
        await tg.start(handler.run)
        async with await anyio.open_process(argv, stderr=subprocess.STDOUT) as follow:
            try:
                out = OutputLines(follow)
                tg.start_soon(out.pump)
                await fabric.wait_matched(keys.log(SYSTEM, "runner-robot"), timeout=20)
                logger.debug("a debug line")
                # a node's rejection on its own log key, then a warning
                key = keys.log(SYSTEM, "analysis")
                rej = Rejection(node="analysis", key="rap/x/data/scan", reason="bad", ts=1, count=2)
                payload, _ = Sealer("analysis").seal_message(key, rej)
                await fabric.publish(key, payload)
                logger.warning("inbox full")
                with anyio.fail_after(20):
                    code = await follow.wait()
                await anyio.sleep(0.1)  # the last output read
            finally:
                await stop_process(follow)
        tg.cancel_scope.cancel()
    assert code == 0, str(out)
    lines = [line for line in out.lines if line]
    assert len(lines) == 3, lines
    # two publishers: their records may come in either order
    (rejected,) = [line for line in lines if "REJECTED" in line]
    assert rejected.endswith("REJECTED analysis 2 sample(s) on rap/x/data/scan: bad")
    logged = [line for line in lines if "REJECTED" not in line]
    assert "DEBUG    runner@robot" in logged[0]
    assert logged[0].endswith("a debug line")
    assert "WARNING  runner@robot" in logged[1]
    assert logged[1].endswith("inbox full")
