"""The dashboard in a real browser (Debian's headless Chromium, driven by Playwright; no
browser is downloaded).

1. The lidar-occlusion model under ``rap up --all`` (a copy of the shipped model on a
   free port, as ``tests/test_rap_up_lidar.py`` runs it): ``rap up`` starts the manager
   beside knowledge and prints its dashboard; the page shows the loop's five components
   alive on their compute nodes; a pause clicked on the page really pauses the
   component (its own ``status`` answer says so, asked over the fabric), and the page
   shows it paused; resume likewise.
2. What comes from the fabric is shown as text: a log line and a rejection reason that
   hold HTML are shown verbatim, and no element of theirs is made.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import anyio
import pytest
from adaptation_manager import Manager, Registry, serve_dashboard
from rap_cli.testing import model_copy, rap_up
from rap_schemas import LogRecord, Rejection, keys
from rap_schemas.admin import ComponentState
from rap_sdk import admin, run_nodes
from rap_sdk.fabric import CONFIG_ENV, Fabric
from rap_sdk.testing import Harness, require_binary

from services.adaptation_manager.tests.loop import loop_nodes

pytestmark = [pytest.mark.anyio]

REPO = Path(__file__).resolve().parents[3]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
SYSTEM = "demo"
WHERE = {
    "monitor": "robot",
    "executor": "robot",
    "analysis": "edge",
    "planner": "edge",
    "legitimate": "edge",
}
UI_TIMEOUT = 30_000
"""ms Playwright waits for the page to show something."""


def _chromium() -> str:
    return require_binary(
        "chromium", hint="Debian's chromium package (.ci/packages installs it: apt-get install "
        "chromium)"
    )  # fmt: skip


async def _state(fabric: Fabric, component: str) -> ComponentState:
    """The component's own answer to ``status``, over the fabric."""
    [reply] = await admin.call(fabric, SYSTEM, component, "status")
    assert reply.ok, reply
    assert reply.status is not None
    return reply.status.state


async def _click(page: Any, component: str, verb: str) -> None:
    from playwright.async_api import expect

    row = page.locator(f'tr[data-component="{component}"]')
    await row.locator(f'button[data-verb="{verb}"]').click()
    result = page.locator("#command-result")
    await expect(result).to_have_text(re.compile(rf"^{verb} {component}: ok"), timeout=UI_TIMEOUT)


@pytest.mark.zenoh
@pytest.mark.slow
@pytest.mark.timeout(180)
async def test_the_page_shows_the_lidar_loop_and_pauses_and_resumes_a_component(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    chromium = _chromium()
    from playwright.async_api import async_playwright, expect

    run = tmp_path / "run"
    async with rap_up(model_copy(MODEL, tmp_path), run, timeout=60) as out:
        with anyio.fail_after(60):
            _, found = await out.match(r"dashboard: (http://127\.0\.0\.1:\d+/)")
            url = found.group(1)
            # rap up says where the dashboard will be as it starts the manager; the page
            # is there once the manager says it is ready (a slow start refused the page)
            await out.match(rf"ready: system '{SYSTEM}', dashboard {re.escape(url)}")
        edge = json.loads((run / "edge" / "up.json").read_text())
        assert edge["dashboard"] == url
        assert "manager" in {c["name"] for c in edge["children"]}
        assert json.loads((run / "robot" / "up.json").read_text())["dashboard"] is None

        monkeypatch.setenv(CONFIG_ENV, str(run / "robot" / "zenoh-client.json5"))
        async with (
            Harness(system=SYSTEM, fabric="zenoh", timeout=30) as h,
            async_playwright() as pw,
        ):
            browser = await pw.chromium.launch(executable_path=chromium, headless=True)
            try:
                page = await browser.new_page()
                await page.goto(url)
                await expect(page.locator("#system")).to_have_text(SYSTEM)
                await expect(page.locator("#link")).to_have_attribute(
                    "data-state", "connected", timeout=UI_TIMEOUT
                )
                for component, node in WHERE.items():
                    row = page.locator(
                        f'section.node[data-node="{node}"] tr[data-component="{component}"]'
                    )
                    await expect(row).to_have_attribute(
                        "data-state", re.compile("^(idle|active)$"), timeout=UI_TIMEOUT
                    )
                    await expect(row.locator('td[data-cell="name"]')).to_have_text(component)
                await expect(
                    page.locator('section.node[data-node="edge"] [data-field="node-name"]')
                ).to_have_text("edge")

                monitor = page.locator('tr[data-component="monitor"]')
                await _click(page, "monitor", "pause")
                assert await _state(h.fabric, "monitor") is ComponentState.PAUSED
                await expect(monitor).to_have_attribute("data-state", "paused")
                await expect(monitor.locator('[data-field="state"]')).to_have_text("paused")

                await _click(page, "monitor", "resume")
                assert await _state(h.fabric, "monitor") in (
                    ComponentState.IDLE,
                    ComponentState.ACTIVE,
                )
                await expect(monitor).to_have_attribute(
                    "data-state", re.compile("^(idle|active)$"), timeout=UI_TIMEOUT
                )
                # the loop runs on: cycles reach the page's timeline
                await expect(page.locator("#cycles tbody tr").first).to_be_visible(
                    timeout=UI_TIMEOUT
                )
            finally:
                await browser.close()


@pytest.mark.timeout(60)
async def test_text_from_the_fabric_is_never_html() -> None:
    chromium = _chromium()
    from playwright.async_api import async_playwright, expect

    evil = '<img src=x onerror="window.pwned=1"><script>window.pwned=2</script>'
    async with Harness(system="esc", timeout=10) as h:
        await h.hold(run_nodes(loop_nodes(), fabric=h.fabric, system="esc", compute_node="edge"))
        manager = Manager(fabric=h.fabric, system="esc", registry=Registry("esc"))
        async with async_playwright() as pw, anyio.create_task_group() as tg:
            await tg.start(manager.run)
            url = await tg.start(serve_dashboard, manager, "127.0.0.1", 0)
            browser = await pw.chromium.launch(executable_path=chromium, headless=True)
            try:
                page = await browser.new_page()
                await page.goto(url)
                await expect(page.locator("#link")).to_have_attribute("data-state", "connected")
                await h.send(
                    keys.log("esc", "monitor"),
                    LogRecord(ts=1, level="ERROR", logger="x", message=evil, component="monitor"),
                )
                await h.send(
                    keys.log("esc", "analysis"),
                    Rejection(node="analysis", key="k", reason=evil, ts=1),
                )
                log = page.locator("#log li")
                await expect(log.filter(has_text="rejected on k")).to_have_count(1)
                await expect(log.filter(has_text=f"monitor: {evil}")).to_have_count(1)
                assert await page.locator("#log img, #log script").count() == 0
                assert await page.evaluate("window.pwned") is None
            finally:
                await browser.close()
            tg.cancel_scope.cancel()
