"""Who may use the model store: with identities the service takes a model request only
signed, by an operator or by an identity ``model_grants`` allows (read: get and list;
write: also put, pin and roll back), and audits each, refusals with who asked. A request
is taken only on its model's own key (the key the routers grant). Without identities
everyone may, as before."""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from pathlib import Path

import msgspec
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_schemas import KbReply, ModelList, ModelPut, keys
from rap_sdk import MemoryBus, MemoryFabric
from rap_sdk.identity import load_signer, load_verifier
from rap_sdk.knowledge import KnowledgeClient, KnowledgeError

from libs.rap_sdk.tests.certs_support import make_certs

pytestmark = pytest.mark.anyio
S = "t"
GRANTS = {"edge.runner": {"occlusion": "write"}, "robot.runner": {"occlusion": "read"}}


class Bed:
    def __init__(self, stack: AsyncExitStack, bus: MemoryBus, certs: Path) -> None:
        self.stack, self.bus, self.certs = stack, bus, certs

    async def client(self, identity: str | None) -> KnowledgeClient:
        """A client signing as ``identity`` (None: unsigned)."""
        fabric = await self.stack.enter_async_context(MemoryFabric(bus=self.bus))
        signer = load_signer(self.certs, identity) if identity else None
        kb = KnowledgeClient(fabric=fabric, system=S, writer=identity or "anon", signer=signer)
        return await self.stack.enter_async_context(kb)


@pytest.fixture(autouse=True)
def _no_identity_from_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """A client without ``signer=`` signs as ``RAP_AS``: here it is unsigned."""
    monkeypatch.delenv("RAP_AS", raising=False)
    monkeypatch.delenv("RAP_CERTS", raising=False)


@asynccontextmanager
async def _bed(tmp_path: Path, *, checked: bool = True) -> AsyncIterator[Bed]:
    certs = make_certs(
        tmp_path / "certs",
        {
            "ops": "operator",
            "edge.runner": "process",
            "robot.runner": "process",
            "robot.robot": "process",
        },
        system=S,
    )
    bus = MemoryBus()
    config = KnowledgeConfig(system=S, model_grants=GRANTS)  # type: ignore[arg-type]
    async with AsyncExitStack() as stack:
        fabric = await stack.enter_async_context(MemoryFabric(bus=bus))
        verifier = load_verifier(certs) if checked else None
        await stack.enter_async_context(open_service(config, fabric=fabric, verifier=verifier))
        yield Bed(stack, bus, certs)


def _audits(caplog: pytest.LogCaptureFixture) -> list[dict[str, object]]:
    return [json.loads(r.getMessage()) for r in caplog.records if r.name == "rap.audit"]


async def test_granted_identities_and_operators_only(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="rap.audit")
    async with _bed(tmp_path) as bed:
        writer = await bed.client("edge.runner")
        reader = await bed.client("robot.runner")
        stranger = await bed.client("robot.robot")
        unsigned = await bed.client(None)
        ops = await bed.client("ops")

        # the writer puts and pins its model
        m1 = await writer.put_model("occlusion", b"v1", tags={"by": "analysis"})
        m2 = await writer.put_model("occlusion", b"v2")
        assert (m1.version, m2.version) == (1, 2)
        assert await writer.pin_model("occlusion", 1) == 1
        # the reader reads it, and may not change it
        versions, pinned = await reader.list_models("occlusion")
        assert ([m.version for m in versions], pinned) == ([1, 2], 1)
        assert (await reader.get_model("occlusion"))[1] == b"v1"
        with pytest.raises(KnowledgeError, match="only read access") as exc:
            await reader.put_model("occlusion", b"mine")
        assert exc.value.code == "denied"
        assert "models: {occlusion: write}" in str(exc.value)
        with pytest.raises(KnowledgeError, match="may not pin model 'occlusion'"):
            await reader.pin_model("occlusion", 2)
        with pytest.raises(KnowledgeError, match="may not roll back model 'occlusion'"):
            await reader.rollback_model("occlusion")
        # a model granted to nobody, an identity granted nothing, nobody at all
        with pytest.raises(KnowledgeError, match="no access to it"):
            await writer.put_model("detector", b"x")
        with pytest.raises(KnowledgeError, match=r"'robot\.robot' may not list model"):
            await stranger.list_models("occlusion")
        with pytest.raises(KnowledgeError, match="unsigned request") as exc:
            await unsigned.get_model("occlusion")
        assert exc.value.code == "denied"
        # an operator may do everything
        assert await ops.pin_model("occlusion", 2) == 2
        assert await ops.rollback_model("occlusion") == 1
        assert (await ops.put_model("detector", b"d")).version == 1
        # nothing the refused asked for was done
        versions, pinned = await ops.list_models("occlusion")
        assert ([m.version for m in versions], pinned) == ([1, 2], 1)

    records = _audits(caplog)
    refused = [r for r in records if r["result"] == "refused"]
    assert {(r["who"], r["verb"]) for r in refused} == {
        ("robot.runner", "model-put"),
        ("robot.runner", "model-pin"),
        ("robot.runner", "model-rollback"),
        ("edge.runner", "model-put"),
        ("robot.robot", "model-list"),
        ("unauthenticated", "model-get"),
    }
    assert all(r["component"] == "knowledge" and r["checked"] for r in refused)
    done = [(r["who"], r["verb"], r["reason"]) for r in records if r["result"] == "ok"]
    assert ("edge.runner", "model-put", "stored version 1") in done
    assert ("edge.runner", "model-pin", "pinned version 1") in done
    assert ("ops", "model-rollback", "rolled back to version 1") in done
    assert ("robot.runner", "model-list", "2 version(s)") in done
    put = next(r for r in records if r["verb"] == "model-put" and r["result"] == "ok")
    assert put["key"] == keys.kb(S, "_models/occlusion")
    assert put["request"] == "occlusion: 2 bytes, sha256 " + m1.sha256[:12]


async def test_a_model_request_is_taken_only_on_its_models_key(tmp_path: Path) -> None:
    async with _bed(tmp_path, checked=False) as bed:
        kb = await bed.client(None)
        await kb.put_model("occlusion", b"v1")
        # a put of another model sent on the key a component is granted: refused, so a
        # grant of one model (or of a knowledge key) gives no other
        data = b"evil"
        put = ModelPut(name="detector", data=data, sha256=hashlib.sha256(data).hexdigest())
        for key in ("_models/occlusion", "lidar_mask"):
            replies = await kb.fabric.query(keys.kb(S, key), msgspec.msgpack.encode(put))
            reply = msgspec.msgpack.decode(replies[0].payload, type=KbReply)
            assert not reply.ok
            assert reply.code == "bad-request"
            assert "send it to rap/t/kb/_models/detector" in reply.error
        replies = await kb.fabric.query(
            keys.kb(S, "_models/occlusion"), msgspec.msgpack.encode(ModelList(name="detector"))
        )
        assert not msgspec.msgpack.decode(replies[0].payload, type=KbReply).ok
        assert (await kb.list_models("detector")) == ([], None)
        # without identities anyone may (unsigned)
        assert (await kb.put_model("occlusion", b"v2")).version == 2
        assert await kb.rollback_model("occlusion") == 1


async def test_a_client_signs_as_its_process_identity(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    async with _bed(tmp_path) as bed:
        # as under rap up with TLS: RAP_AS and RAP_CERTS, no signer given
        monkeypatch.setenv("RAP_CERTS", str(bed.certs))
        monkeypatch.setenv("RAP_AS", "edge.runner")
        kb = await bed.client(None)
        assert (await kb.put_model("occlusion", b"v1")).version == 1
        assert kb.signer is not None
        assert kb.signer.name == "edge.runner"
        # an identity without its files: the error names the file and the fix
        monkeypatch.setenv("RAP_AS", "nobody")
        lost = await bed.client(None)
        with pytest.raises(KnowledgeError, match=r"cannot sign .*nobody\.pem: no such file"):
            await lost.list_models("occlusion")
