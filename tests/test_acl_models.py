"""The model store with TLS and access control on, granted by the system model.

A router runs as ``rap up`` runs it, with the access control derived from the lidar
model in which the analysis (hosted by ``edge.runner``) declares ``models: {occlusion:
write}`` and the monitor (hosted by ``robot.runner``) ``models: {occlusion: read}``; the
knowledge service runs as ``edge.knowledge`` with the system's CA and the grants ``rap
up`` hands it. Each session presents its own certificate (``rap certs``) and signs its
model requests with it. The granted writer puts and pins; the reader lists and gets, and
its put is refused by the service and audited with its identity; a process the model
grants nothing cannot even ask (the router refuses its query and logs its identity); an
operator rolls back.
"""

from __future__ import annotations

import json
import logging
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from pathlib import Path

import anyio
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_cli.acl import model_grants
from rap_cli.testing import SecuredRouter, model_copy, secured_router
from rap_schemas import keys
from rap_sdk.fabric import ZenohFabric
from rap_sdk.identity import load_signer, load_verifier
from rap_sdk.knowledge import KnowledgeClient, KnowledgeError

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.timeout(120)]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
S = "demo"
OCCLUSION = keys.kb(S, "_models/occlusion")


class Bed:
    def __init__(self, router: SecuredRouter, stack: AsyncExitStack) -> None:
        self.router, self.certs, self.log, self.stack = router, router.certs, router.log, stack

    async def session(self, identity: str) -> ZenohFabric:
        """A RAP process's session as ``identity``, open until the bed closes."""
        return await self.stack.enter_async_context(self.router.session(identity))

    async def client(self, identity: str) -> KnowledgeClient:
        """A knowledge client of ``identity``'s session, signing as it."""
        kb = KnowledgeClient(
            fabric=await self.session(identity),
            system=S,
            writer=identity,
            timeout=1.0,
            signer=load_signer(self.certs, identity),
        )
        return await self.stack.enter_async_context(kb)


@asynccontextmanager
async def _bed(tmp_path: Path) -> AsyncIterator[Bed]:
    model = model_copy(MODEL, tmp_path)
    text = model.read_text()
    for old, new in (
        ("    writes: [lidar_mask, handling_anomaly]\n", "    models: {occlusion: write}\n"),
        ("    writes: [laser_scan, odometry, obstacle_map]\n", "    models: {occlusion: read}\n"),
    ):
        assert text.count(old) == 1
        text = text.replace(old, old + new)
    model.write_text(text)
    async with secured_router(model, tmp_path) as router, AsyncExitStack() as stack:
        bed = Bed(router, stack)
        # the knowledge service as rap up runs it: its identity, the CA, the grants
        config = KnowledgeConfig(system=S, model_grants=model_grants(router.plan))  # type: ignore[arg-type]
        await stack.enter_async_context(
            open_service(
                config,
                fabric=await bed.session("edge.knowledge"),
                verifier=load_verifier(router.certs),
            )
        )
        yield bed


async def _answered(kb: KnowledgeClient) -> None:
    """Wait until the service's queryable is reachable from ``kb``'s session."""
    with anyio.fail_after(15):
        while True:
            try:
                await kb.list_models("occlusion")
                return
            except KnowledgeError as exc:
                if exc.code != "unavailable":
                    raise
            await anyio.sleep(0.1)


async def test_granted_components_use_their_models_and_others_are_refused(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="rap.audit")
    async with _bed(tmp_path) as bed:
        writer = await bed.client("edge.runner")  # hosts the analysis: occlusion, write
        reader = await bed.client("robot.runner")  # hosts the monitor: occlusion, read
        stranger = await bed.client("robot.robot")  # the simulator: no model
        ops = await bed.client("ops")
        await _answered(writer)

        # a granted component puts and pins
        assert (await writer.put_model("occlusion", b"v1", tags={"by": "analysis"})).version == 1
        assert (await writer.put_model("occlusion", b"v2")).version == 2
        assert await writer.pin_model("occlusion", 1) == 1

        # a reader reads; its put gets through the router (a query on its model's key)
        # and is refused by the service, audited with its identity
        await _answered(reader)
        assert (await reader.get_model("occlusion"))[1] == b"v1"
        with pytest.raises(KnowledgeError, match="only read access") as exc:
            await reader.put_model("occlusion", b"the reader's")
        assert exc.value.code == "denied"

        # a process granted no model cannot ask at all: the router refuses its query
        # (it never reaches the service) and logs who tried
        with pytest.raises(KnowledgeError, match="no knowledge service answered"):
            await stranger.put_model("occlusion", b"the simulator's")
        at = await bed.log.line(f"refused: robot.robot may not query (ingress) on {OCCLUSION}")
        assert "robot.robot" in bed.log.lines[at]
        # nor another model than its own, for a granted one
        with pytest.raises(KnowledgeError, match="no knowledge service answered"):
            await writer.put_model("detector", b"another model")
        await bed.log.line(
            f"refused: edge.runner may not query (ingress) on {keys.kb(S, '_models/detector')}"
        )

        # an operator may do everything
        assert await ops.pin_model("occlusion", 2) == 2
        assert await ops.rollback_model("occlusion") == 1
        versions, pinned = await ops.list_models("occlusion")
        assert ([m.version for m in versions], pinned) == ([1, 2], 1)

    records = [json.loads(r.getMessage()) for r in caplog.records if r.name == "rap.audit"]
    refused = [(r["who"], r["verb"]) for r in records if r["result"] == "refused"]
    assert refused == [("robot.runner", "model-put")]
    done = {(r["who"], r["verb"]) for r in records if r["result"] == "ok"}
    assert {
        ("edge.runner", "model-put"),
        ("edge.runner", "model-pin"),
        ("ops", "model-pin"),
        ("ops", "model-rollback"),
    } <= done
