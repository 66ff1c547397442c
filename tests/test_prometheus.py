"""A real Prometheus server scrapes a RAP process's metrics endpoint: nodes on real
Zenoh sessions handle a known number of samples, and Prometheus's HTTP API gives that
count back (and the latency histogram's), labelled by system, compute node, component
and stage."""

from __future__ import annotations

import json
import subprocess
import urllib.error
import urllib.parse
import urllib.request
from functools import partial
from pathlib import Path
from typing import Any

import anyio
import pytest
from prometheus_client import CollectorRegistry
from rap_schemas import Message
from rap_sdk import Context, Node
from rap_sdk.metrics import RuntimeCollector, serve_metrics
from rap_sdk.testing import Harness, Record, free_port, require_binary, stop_process

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.timeout(90)]

S = "prom"
CALLS = 25


class Tick(Message, frozen=True):
    TYPE = "test.Tick/1"

    n: int


def _handled(h: Harness, node: str, n: int, _: Record) -> bool:
    return len([t for t in h.traces(node) if t.ended]) == n


def _get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            return int(resp.status), bytes(resp.read())
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()
    except OSError:
        return 0, b""


async def _query(base: str, expr: str) -> list[dict[str, Any]]:
    url = f"{base}/api/v1/query?" + urllib.parse.urlencode({"query": expr})
    status, body = await anyio.to_thread.run_sync(_get, url)
    assert status == 200, (status, body)
    doc = json.loads(body)
    assert doc["status"] == "success", doc
    result: list[dict[str, Any]] = doc["data"]["result"]
    return result


async def _value(base: str, expr: str, want: float, timeout: float = 30.0) -> dict[str, Any]:
    """The one series of ``expr`` once its value is ``want`` (scrapes come every second)."""
    got: list[dict[str, Any]] = []
    with anyio.move_on_after(timeout):
        while True:
            got = await _query(base, expr)
            if len(got) == 1 and float(got[0]["value"][1]) == want:
                return got[0]
            await anyio.sleep(0.25)
    raise AssertionError(f"{expr}: never {want} within {timeout} s; last answer: {got}")


async def test_prometheus_scrapes_the_counts_the_loop_caused(tmp_path: Path) -> None:
    binary = require_binary("prometheus", hint="apt-get install prometheus")
    mon = Node("mon", stage="monitor")
    ana = Node("ana", stage="analyse")

    @mon.on_data("tick")
    async def on_tick(ctx: Context, tick: Tick) -> None:
        await ctx.emit("new-data")

    @ana.on_event("new-data")
    async def detect(ctx: Context) -> None:
        pass

    async with Harness(system=S, fabric="zenoh", isolate=True, timeout=20) as h:
        group = await h.start(mon, ana)
        registry = CollectorRegistry(auto_describe=False)
        registry.register(RuntimeCollector(lambda: group.runtimes, system=S, compute_node="robot"))
        with serve_metrics(registry, "127.0.0.1", 0) as metrics:
            port = free_port()
            base = f"http://127.0.0.1:{port}"
            config = tmp_path / "prometheus.yml"
            config.write_text(
                "global:\n"
                "  scrape_interval: 1s\n"
                "  evaluation_interval: 1s\n"
                "scrape_configs:\n"
                "  - job_name: rap\n"
                "    scrape_interval: 1s\n"
                "    scrape_timeout: 900ms\n"
                "    static_configs:\n"
                f"      - targets: ['127.0.0.1:{metrics.port}']\n",
                encoding="utf-8",
            )
            argv = [
                binary,
                f"--config.file={config}",
                f"--storage.tsdb.path={tmp_path / 'data'}",
                f"--web.listen-address=127.0.0.1:{port}",
                "--log.level=warn",
            ]
            async with await anyio.open_process(
                argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
            ) as prom:
                try:
                    with anyio.fail_after(30):
                        while (await anyio.to_thread.run_sync(_get, f"{base}/-/ready"))[0] != 200:
                            assert prom.returncode is None, "prometheus exited"
                            await anyio.sleep(0.1)
                    # real handler calls, each sample over a Zenoh session
                    for i in range(CALLS):
                        await h.publish("tick", Tick(n=i))
                        await h.wait_for(partial(_handled, h, "ana", i + 1))
                    mine = f'system="{S}",compute_node="robot"'
                    handled = await _value(
                        base, f'rap_handled_total{{component="mon",{mine}}}', CALLS
                    )
                    assert handled["metric"]["stage"] == "monitor"
                    assert handled["metric"]["job"] == "rap"
                    await _value(base, f'rap_handled_total{{component="ana",{mine}}}', CALLS)
                    await _value(
                        base,
                        f'rap_handler_latency_seconds_count{{component="ana",{mine}}}',
                        CALLS,
                    )
                    await _value(base, f'rap_cycles_total{{stage="monitor",{mine}}}', CALLS)
                    await _value(base, f'rap_failed_total{{component="mon",{mine}}}', 0)
                finally:
                    await stop_process(prom, grace=10)
            assert prom.returncode == 0, "prometheus did not stop cleanly"
