"""The dashboard's server over real HTTP: the page and its headers, /metrics, the
WebSocket (a snapshot, pushed batches, commands that really pause a component), the POST
form of a command, and what it refuses (another origin, a body that is not JSON, bad
messages)."""

from __future__ import annotations

import contextlib
import json
from collections.abc import AsyncIterator
from typing import Any

import aiohttp
import anyio
import pytest
from adaptation_manager import Manager, Registry, serve_dashboard
from rap_schemas import keys
from rap_schemas.admin import ComponentState
from rap_sdk import admin, run_nodes
from rap_sdk.testing import Harness

from services.adaptation_manager.tests.loop import Waiter, loop_nodes

pytestmark = pytest.mark.anyio

S = "dash"


@contextlib.asynccontextmanager
async def dashboard() -> AsyncIterator[tuple[Harness, Manager, str]]:
    async with Harness(system=S, timeout=10) as h:
        await h.hold(run_nodes(loop_nodes(), fabric=h.fabric, system=S, compute_node="edge"))
        waiter = Waiter()
        manager = Manager(fabric=h.fabric, system=S, registry=Registry(S), status_interval=0.2)
        manager.on_poll = waiter.poke
        async with anyio.create_task_group() as tg:
            await tg.start(manager.run)
            url = await tg.start(serve_dashboard, manager, "127.0.0.1", 0)
            reg = manager.registry
            waiter.inner = reg.on_change  # the hub's
            reg.on_change = waiter.hook
            await waiter.until(lambda: len([c for c in reg.components.values() if c.answers]) == 5)
            yield h, manager, url
            tg.cancel_scope.cancel()


async def next_json(ws: aiohttp.ClientWebSocketResponse, pred: Any) -> dict[str, Any]:
    with anyio.fail_after(10):
        while True:
            msg = await ws.receive()
            assert msg.type == aiohttp.WSMsgType.TEXT, msg
            data: dict[str, Any] = json.loads(msg.data)
            if pred(data):
                return data


async def test_page_metrics_websocket_and_commands() -> None:
    async with dashboard() as (h, _, url), aiohttp.ClientSession() as http:
        async with http.get(url) as page:
            assert page.status == 200
            assert "script-src 'self'" in page.headers["Content-Security-Policy"]
            assert '<script src="/static/app.js"' in await page.text()
        async with http.get(url + "static/app.js") as js:
            body = await js.text()
            assert "textContent" in body
            assert "innerHTML" not in body  # nothing from the fabric is parsed as HTML
        async with http.get(url + "metrics") as metrics:
            text = await metrics.text()
            assert "rap_manager_components{" in text
            assert 'rap_manager_components{state="idle"}' in text
        async with http.ws_connect(url + "ws") as ws:
            snap = await next_json(ws, lambda d: d["t"] == "snapshot")
            by_name = {c["name"]: c for c in snap["components"]}
            assert by_name["monitor"]["compute_node"] == "edge"
            # a scan: its cycle and plan are pushed as they happen
            await h.send(keys.data(S, "scan"))
            await next_json(
                ws,
                lambda d: (
                    d["t"] == "batch"
                    and any(i["k"] == "plan" and i["v"]["status"] == "executed" for i in d["items"])
                ),
            )
            await ws.send_str(
                json.dumps({"t": "command", "id": 7, "component": "monitor", "verb": "pause"})
            )
            result = await next_json(ws, lambda d: d["t"] == "result")
            assert (result["id"], result["ok"], result["state"]) == (7, True, "paused")
            [reply] = await admin.call(h.fabric, S, "monitor", "status")
            assert reply.status is not None
            assert reply.status.state is ComponentState.PAUSED
            await next_json(
                ws,
                lambda d: (
                    d["t"] == "batch"
                    and any(
                        i["k"] == "component"
                        and i["v"]["name"] == "monitor"
                        and i["v"]["state"] == "paused"
                        for i in d["items"]
                    )
                ),
            )
            await ws.send_str("{not json")
            error = await next_json(ws, lambda d: d["t"] == "error")
            assert "bad message" in error["message"]
        # the POST form
        async with http.post(url + "api/admin/monitor/resume", json={}) as res:
            assert res.status == 200
            assert (await res.json())["state"] in ("idle", "active")
        async with http.post(url + "api/admin/monitor/swap", json={}) as res:
            assert res.status == 409
        async with http.post(url + "api/admin/monitor/pause", data="x") as res:
            assert res.status == 415
        async with http.get(url + "api/trace?last=1&executed=1") as res:
            trace = await res.json()
            assert trace["ok"], trace
            assert [s["node"] for s in trace["trace"]["steps"]][-1] == "executor"


async def test_requests_from_another_origin_are_refused() -> None:
    async with dashboard() as (h, _, url), aiohttp.ClientSession() as http:
        evil = {"Origin": "http://evil.example"}
        with pytest.raises(aiohttp.WSServerHandshakeError) as exc:
            await http.ws_connect(url + "ws", headers=evil)
        assert exc.value.status == 403
        async with http.post(url + "api/admin/monitor/pause", json={}, headers=evil) as res:
            assert res.status == 403
        [reply] = await admin.call(h.fabric, S, "monitor", "status")
        assert reply.status is not None
        assert reply.status.state is not ComponentState.PAUSED
        # the page's own origin is accepted
        own = {"Origin": url.rstrip("/")}
        async with http.post(url + "api/admin/monitor/pause", json={}, headers=own) as res:
            assert res.status == 200
