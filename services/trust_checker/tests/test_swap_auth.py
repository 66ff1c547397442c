"""The attack on the trust checker's hot swap over the fabric: a peer without operator
credentials replaces the MAPLE-K stage-order spec by one that says
``stage_order_ok = true`` whatever happens. A checker with identities refuses it
(unsigned, signed by a process, signed by another CA's 'operator', signed for something
else, replayed), keeps judging with its spec, and audits every attempt with who made it;
an operator's swap is taken and audited. Real Zenoh sessions on loopback."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from rap_schemas import Stage, StageTrace, TrustOutput, TrustSpecUpdate, keys
from rap_schemas.admin import AuditRecord
from rap_sdk import QueryError, Sealer, ZenohConfig, ZenohFabric
from rap_sdk.envelope import typed_decoder
from rap_sdk.fabric import free_port
from rap_sdk.identity import load_signer, load_verifier
from trust_checker.config import FabricConfig, ServiceConfig
from trust_checker.io.auth import fabric_swap
from trust_checker.io.specs import load_text
from trust_checker.service import TrustService, open_service
from trust_checker.specs import maplek_specs

from libs.rap_sdk.tests.certs_support import make_certs

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh]

SYS = "tb1"
NODE = "trust_stage_order"
EVIL = "in stage: Str\nout stage_order_ok: Bool\nstage_order_ok = true\n"
PEOPLE = {"alice": "operator", "robot.trust-lidar": "process"}
_open_output = typed_decoder(TrustOutput)


def audits(caplog: pytest.LogCaptureFixture) -> list[AuditRecord]:
    return [
        msgspec.json.decode(r.getMessage(), type=AuditRecord)
        for r in caplog.records
        if r.name == "rap.audit"
    ]


class Robot:
    """The peer: sends trace records, collects the checker's outputs."""

    def __init__(self, fabric: ZenohFabric) -> None:
        self.fabric = fabric
        self.sealer = Sealer("robot")
        self.outputs: list[TrustOutput] = []
        self.changed = anyio.Event()

    async def collect(self, sub: Any) -> None:
        async for sample in sub:
            self.outputs.append(_open_output(sample.payload).body)
            self.changed.set()

    async def start(self, node: str, stage: Stage, cycle: bytes) -> TrustOutput:
        """A handler of ``stage`` starts in ``cycle``: the checker's verdict on it."""
        n = len(self.outputs)
        rec = StageTrace(
            node=node,
            handler="h",
            phase="start",
            trigger=b"\x01" * 16,
            trigger_key=keys.event(SYS, "x"),
            cycle=cycle,
            ts=1,
            stage=stage,
        )
        key = keys.trace(SYS, node)
        payload, _ = self.sealer.seal_message(key, rec, cycle=cycle)
        await self.fabric.publish(key, payload)
        with anyio.fail_after(5):
            while len(self.outputs) <= n:
                self.changed = anyio.Event()
                await self.changed.wait()
        return self.outputs[n]


@asynccontextmanager
async def running(verifier: Any = None) -> AsyncIterator[tuple[TrustService, Robot]]:
    port = free_port()
    config = ServiceConfig(node=NODE, verdicts=False, fabric=FabricConfig(system=SYS))
    spec = load_text(maplek_specs()["stage_order"], "stage_order.dsrv")
    async with (
        ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"])) as fab,
        ZenohFabric(ZenohConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as peer_fab,
        open_service(config, spec, fabric=fab, verifier=verifier) as service,
        anyio.create_task_group() as tg,
    ):
        robot = Robot(peer_fab)
        sub = peer_fab.subscribe(keys.pattern(SYS, keys.Kind.TRUST))
        tg.start_soon(robot.collect, sub)
        await peer_fab.wait_matched(keys.trace(SYS, "planner"))
        await fab.wait_matched(keys.trust(SYS, "stage_order_ok"))
        await peer_fab.wait_matched(keys.admin(SYS, NODE, "swap"), queryable=True)
        try:
            yield service, robot
        finally:
            sub.close()
            tg.cancel_scope.cancel()


@pytest.fixture
def certs(tmp_path: Path) -> Path:
    return make_certs(tmp_path / "certs", PEOPLE, system=SYS)


async def test_a_swap_without_operator_credentials_is_refused_and_the_spec_stays(
    certs: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="rap.audit")
    key = keys.admin(SYS, NODE, "swap")
    foreign = make_certs(tmp_path / "foreign", {"alice": "operator"})
    async with running(load_verifier(certs)) as (service, robot):
        spec_before = service.runner
        fab = robot.fabric
        # unsigned: the attack as it worked before identities
        with pytest.raises(QueryError, match="swap refused: unsigned request"):
            await fabric_swap(fab, key, EVIL)
        # signed, but by a process of the system (a robot's checker identity)
        with pytest.raises(QueryError) as info:
            await fabric_swap(fab, key, EVIL, signer=load_signer(certs, "robot.trust-lidar"))
        assert (
            "'robot.trust-lidar' (role process) may not swap the spec of trust_stage_order: "
            "that needs the role operator" in str(info.value)
        )
        # an 'operator' certificate of another CA
        with pytest.raises(QueryError, match="is not issued by this system's CA"):
            await fabric_swap(fab, key, EVIL, signer=load_signer(foreign, "alice"))
        # alice's real signature, taken from a harmless request, put on the evil spec
        alice = load_signer(certs, "alice")
        harmless, _ = Sealer("x").seal_message(key, TrustSpecUpdate(spec="in a: Int\n"))
        evil, _ = Sealer("x").seal_message(key, TrustSpecUpdate(spec=EVIL))
        (r,) = await fab.query(key, evil, attachment=alice.attachment(key, "swap", harmless))
        assert not r.ok
        assert b"swap refused: bad signature" in r.payload

        # the checker still judges with its own spec: execute opening a cycle is wrong
        verdict = await robot.start("executor", Stage.EXECUTE, bytes(range(16)))
        assert (verdict.stream, verdict.value) == ("stage_order_ok", False)
        assert service.runner is spec_before
        assert service.session.stats.swaps == 0
        transport = service.fabric
        assert transport is not None
        assert transport.stats.rejections.by_reason == {
            "swap refused: unsigned": 1,
            "swap refused: not an operator": 1,
            "swap refused: certificate refused": 1,
            "swap refused: bad signature": 1,
        }
    rows = [(a.verb, a.component, a.result, a.who, a.role) for a in audits(caplog)]
    assert rows == [
        ("swap", NODE, "refused", "unauthenticated", ""),
        ("swap", NODE, "refused", "robot.trust-lidar", "process"),
        ("swap", NODE, "refused", "unauthenticated", ""),
        ("swap", NODE, "refused", "unauthenticated", ""),
    ]
    first = audits(caplog)[0]
    assert first.key == key
    assert first.via == "fabric"
    assert first.request.startswith(f"spec <swap>: {len(EVIL)} characters, sha256 ")
    refused = [r for r in caplog.records if r.name == "rap.audit"]
    assert all(r.levelname == "WARNING" for r in refused)


async def test_an_operators_swap_is_taken_once_and_audited(
    certs: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="rap.audit")
    monkeypatch.setenv("RAP_CERTS", str(certs))  # the checker takes its CA from there
    key = keys.admin(SYS, NODE, "swap")
    async with running() as (service, robot):
        alice = load_signer(certs, "alice")
        verdict = await robot.start("executor", Stage.EXECUTE, bytes(range(16)))
        assert verdict.value is False
        payload, _ = Sealer("alice").seal_message(key, TrustSpecUpdate(spec=EVIL, path="ok.dsrv"))
        att = alice.attachment(key, "swap", payload)
        (reply,) = await robot.fabric.query(key, payload, attachment=att, timeout=5)
        assert reply.ok, reply.payload
        assert service.session.stats.swaps == 1
        # what the operator decided now holds
        verdict = await robot.start("executor", Stage.EXECUTE, bytes(range(1, 17)))
        assert verdict.value is True
        # the same request again: a replay, refused
        (again,) = await robot.fabric.query(key, payload, attachment=att, timeout=5)
        assert not again.ok
        assert b"swap refused: replayed request" in again.payload
        assert service.session.stats.swaps == 1
        # a spec with problems, from the operator: taken as a request, refused as a spec
        status = await fabric_swap(robot.fabric, key, "in x: Int\nout y\ny = z\n", signer=alice)
        assert not status.ok
    rows = [(a.result, a.who, a.role, a.checked) for a in audits(caplog)]
    assert rows == [
        ("ok", "alice", "operator", True),
        ("refused", "alice", "operator", True),
        ("error", "alice", "operator", True),
    ]
    ok = audits(caplog)[0]
    assert ok.request.startswith(f"spec ok.dsrv: {len(EVIL)} characters")
    assert ok.reason.startswith("swapped at tick 1: inputs stage; outputs stage_order_ok")
    assert "replayed request" in audits(caplog)[1].reason
    assert audits(caplog)[2].reason.startswith("the spec has problems: <swap>:3:5:")


async def test_without_identities_a_swap_is_taken_as_before(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="rap.audit")
    monkeypatch.delenv("RAP_CERTS", raising=False)
    key = keys.admin(SYS, NODE, "swap")
    async with running() as (service, robot):
        status = await fabric_swap(robot.fabric, key, EVIL)
        assert status.ok
        assert service.session.stats.swaps == 1
    (rec,) = audits(caplog)
    assert (rec.result, rec.who, rec.checked) == ("ok", "unauthenticated", False)
