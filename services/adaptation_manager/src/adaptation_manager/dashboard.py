"""The live dashboard: one page, its script and style (packaged, no build step, nothing
from a CDN), changes pushed over a WebSocket, and ``/metrics``.

    GET  /                       the page
    GET  /static/app.js|app.css  its script and style
    GET  /ws                     WebSocket: a ``snapshot``, then ``batch`` messages as the
                                 registry changes; the page sends ``command`` messages
                                 ({"t": "command", "id": 1, "component": "monitor",
                                 "verb": "pause"}) and gets a ``result`` for each
    POST /api/admin/<component>/<verb>   the same command without the WebSocket (JSON body)
    GET  /api/state              the snapshot as JSON
    GET  /api/trace?cycle=HEX    one cycle's causal chain (``last=1`` for the latest)
    GET  /metrics                the manager's Prometheus counters

Changes are coalesced for ``flush_delay`` s (a component that changes ten times in that
window is sent once) and sent to every page; a page that does not keep up is
disconnected (its script reconnects and gets a fresh snapshot). The page is served with a
Content-Security-Policy that allows its own script only, and sets every value from the
fabric as text (``textContent``), never as HTML. Requests that change something (the
WebSocket, the POST) must come from the page's own origin.
"""

from __future__ import annotations

import contextlib
import logging
from collections import OrderedDict, deque
from importlib import resources
from typing import Any, Final
from urllib.parse import urlsplit

import anyio
import msgspec
from aiohttp import WSMsgType, web
from anyio.abc import TaskStatus
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from .service import Manager
from .state import Registry, _Cycle

__all__ = ["Hub", "make_app", "serve_dashboard"]

log = logging.getLogger("adaptation_manager.dashboard")

CLIENT_QUEUE: Final = 256
"""Batches waiting for one page; a page this far behind is disconnected."""
MAX_COMMAND: Final = 4096
"""Bytes of a message from a page."""
APPENDED: Final = 500
"""Log lines, alerts and verdicts kept for the next batch (older ones are dropped)."""
CSP: Final = (
    "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; "
    "img-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)
_encode = msgspec.json.encode


class _Command(msgspec.Struct, kw_only=True):
    t: str
    id: int = 0
    component: str = ""
    verb: str = ""


_command = msgspec.json.Decoder(_Command).decode


class _Client:
    def __init__(self) -> None:
        self.send, self.recv = anyio.create_memory_object_stream[str](CLIENT_QUEUE)
        self.overflowed = anyio.Event()


class Hub:
    """Collects the registry's changes and pushes them to the connected pages."""

    def __init__(self, registry: Registry, *, flush_delay: float = 0.05) -> None:
        self.registry = registry
        self.flush_delay = flush_delay
        self.clients: set[_Client] = set()
        self._pending: OrderedDict[tuple[str, str], Any] = OrderedDict()
        self._appended: deque[tuple[str, Any]] = deque(maxlen=APPENDED)
        self._wake = anyio.Event()
        self.batches = 0
        registry.on_change = self.changed

    def changed(self, kind: str, view: Any) -> None:
        """The registry's change hook: keyed views replace their earlier change. With no
        page connected nothing is kept (a page gets a snapshot when it connects)."""
        if not self.clients:
            return
        if kind == "component":
            self._pending[(kind, view.name)] = view
        elif kind == "cycle":
            self._pending[(kind, view.hex)] = view
        elif kind == "plan":
            self._pending[(kind, view.plan)] = view
        elif kind == "trust":
            self._pending[(kind, view.stream)] = view
        else:
            self._appended.append((kind, view))
        if not self._wake.is_set():
            self._wake.set()

    def snapshot(self) -> str:
        data = self.registry.snapshot()
        data["t"] = "snapshot"
        return _encode(data).decode()

    def attach(self) -> _Client:
        client = _Client()
        self.clients.add(client)
        self.registry.metrics.clients.set(len(self.clients))
        return client

    def detach(self, client: _Client) -> None:
        self.clients.discard(client)
        client.send.close()
        client.recv.close()
        self.registry.metrics.clients.set(len(self.clients))

    def _batch(self) -> str | None:
        items: list[dict[str, Any]] = []
        reg = self.registry
        for (kind, _), view in self._pending.items():
            if isinstance(view, _Cycle):
                if view.uid not in reg.cycles:
                    continue  # left the history already
                items.append({"k": kind, "v": reg.cycle_view(view)})
            else:
                items.append({"k": kind, "v": view})
        items.extend({"k": kind, "v": view} for kind, view in self._appended)
        self._pending.clear()
        self._appended.clear()
        if not items:
            return None
        return _encode({"t": "batch", "items": items, "counters": reg.counters()}).decode()

    async def run(self) -> None:
        """Push changes until cancelled."""
        while True:
            await self._wake.wait()
            self._wake = anyio.Event()
            await anyio.sleep(self.flush_delay)  # coalesce what changes meanwhile
            text = self._batch()
            if text is None:
                continue
            self.batches += 1
            for client in list(self.clients):
                try:
                    client.send.send_nowait(text)
                except anyio.WouldBlock:
                    client.overflowed.set()
                except (anyio.BrokenResourceError, anyio.ClosedResourceError):
                    self.clients.discard(client)


def _same_origin(request: web.Request) -> bool:
    """No ``Origin`` (not a browser's cross-site request), or the page's own."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    return urlsplit(origin).netloc.lower() == request.host.lower()


class _Assets(msgspec.Struct):
    html: bytes
    js: bytes
    css: bytes


def load_assets() -> _Assets:
    """The page, its script and style, from the package (call it in a worker thread)."""
    files = resources.files("adaptation_manager") / "static"
    return _Assets(
        html=(files / "index.html").read_bytes(),
        js=(files / "app.js").read_bytes(),
        css=(files / "app.css").read_bytes(),
    )


def make_app(manager: Manager, hub: Hub, assets: _Assets) -> web.Application:
    """The aiohttp application of the dashboard."""
    sockets: set[web.WebSocketResponse] = set()
    headers = {
        "Content-Security-Policy": CSP,
        "X-Content-Type-Options": "nosniff",
        "Referrer-Policy": "no-referrer",
        "Cache-Control": "no-store",
    }

    def static(body: bytes, content_type: str) -> Any:
        async def handler(request: web.Request) -> web.Response:
            return web.Response(
                body=body, content_type=content_type, charset="utf-8", headers=headers
            )

        return handler

    async def metrics(request: web.Request) -> web.Response:
        body = generate_latest(manager.registry.metrics.registry)
        return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})

    async def state(request: web.Request) -> web.Response:
        return web.Response(text=hub.snapshot(), content_type="application/json", headers=headers)

    async def trace(request: web.Request) -> web.Response:
        q = request.query
        if q.get("last"):
            payload = _encode({"last": True, "executed": bool(q.get("executed"))})
        else:
            payload = q.get("cycle", "")[:64].encode("ascii", "replace")
        reply = manager.trace(payload)
        return web.Response(body=_encode(reply), content_type="application/json", headers=headers)

    async def post_admin(request: web.Request) -> web.Response:
        if not _same_origin(request):
            raise web.HTTPForbidden(text="cross-origin request refused")
        if request.content_type != "application/json":
            raise web.HTTPUnsupportedMediaType(text="send the command with a JSON body ({})")
        result = await manager.command(request.match_info["component"], request.match_info["verb"])
        return web.Response(
            body=_encode(result),
            status=200 if result.ok else 409,
            content_type="application/json",
            headers=headers,
        )

    async def websocket(request: web.Request) -> web.StreamResponse:
        if not _same_origin(request):
            raise web.HTTPForbidden(text="cross-origin WebSocket refused")
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=MAX_COMMAND)
        await ws.prepare(request)
        sockets.add(ws)
        client = hub.attach()
        try:
            await ws.send_str(hub.snapshot())
            async with anyio.create_task_group() as tg:
                tg.start_soon(_pump, ws, client)
                async for msg in ws:
                    if msg.type != WSMsgType.TEXT:
                        continue
                    tg.start_soon(_on_message, ws, manager, msg.data)
                tg.cancel_scope.cancel()
        finally:
            hub.detach(client)
            sockets.discard(ws)
        return ws

    async def on_shutdown(app: web.Application) -> None:
        for ws in list(sockets):
            with contextlib.suppress(ConnectionError, RuntimeError):
                await ws.close(code=1001, message=b"the manager is stopping")

    app = web.Application(client_max_size=MAX_COMMAND * 4)
    app.router.add_get("/", static(assets.html, "text/html"))
    app.router.add_get("/static/app.js", static(assets.js, "text/javascript"))
    app.router.add_get("/static/app.css", static(assets.css, "text/css"))
    app.router.add_get("/ws", websocket)
    app.router.add_get("/metrics", metrics)
    app.router.add_get("/api/state", state)
    app.router.add_get("/api/trace", trace)
    app.router.add_post("/api/admin/{component}/{verb}", post_admin)
    app.on_shutdown.append(on_shutdown)
    return app


async def _pump(ws: web.WebSocketResponse, client: _Client) -> None:
    """Send the hub's batches to one page; a page that falls behind is disconnected."""
    async with anyio.create_task_group() as tg:

        async def overflow() -> None:
            await client.overflowed.wait()
            log.warning("dashboard: a page fell %d batches behind: disconnected", CLIENT_QUEUE)
            await ws.close(code=1013, message=b"too slow: reconnect for a fresh snapshot")
            tg.cancel_scope.cancel()

        tg.start_soon(overflow)
        async for text in client.recv:
            await ws.send_str(text)
        tg.cancel_scope.cancel()


async def _on_message(ws: web.WebSocketResponse, manager: Manager, data: str) -> None:
    try:
        cmd = _command(data)
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        manager.registry.unreadable("dashboard", "ws", f"bad message from a page: {exc}")
        await ws.send_str(_encode({"t": "error", "message": f"bad message: {exc}"}).decode())
        return
    if cmd.t != "command":
        await ws.send_str(
            _encode({"t": "error", "id": cmd.id, "message": f"unknown {cmd.t[:40]!r}"}).decode()
        )
        return
    result = await manager.command(cmd.component, cmd.verb)
    reply = msgspec.to_builtins(result)
    reply.update(t="result", id=cmd.id)
    with contextlib.suppress(ConnectionError, RuntimeError):
        await ws.send_str(_encode(reply).decode())


async def serve_dashboard(
    manager: Manager,
    host: str,
    port: int,
    *,
    task_status: TaskStatus[str] = anyio.TASK_STATUS_IGNORED,
) -> None:
    """Serve the dashboard on ``host:port`` (0: a free port) until cancelled; reports its
    URL (``http://host:port/``) when it listens."""
    hub = Hub(manager.registry)
    assets = await anyio.to_thread.run_sync(load_assets)
    app = make_app(manager, hub, assets)
    runner = web.AppRunner(app, access_log=None, shutdown_timeout=2.0)
    await runner.setup()
    try:
        site = web.TCPSite(runner, host, port)
        await site.start()
        bound = runner.addresses[0]
        url = f"http://{_host(host)}:{bound[1]}/"
        log.info("dashboard: %s", url)
        task_status.started(url)
        await hub.run()
    finally:
        with anyio.CancelScope(shield=True):
            await runner.cleanup()


def _host(host: str) -> str:
    return f"[{host}]" if ":" in host and not host.startswith("[") else host
