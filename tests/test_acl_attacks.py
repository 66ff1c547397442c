"""Access control derived from the model, against the attacks of a hostile peer.

A router runs as ``rap up`` runs it (``python -m rap_cli.router`` with the config
``router_config`` writes for the lidar-occlusion model with ``fabric: {tls: true}``), and
sessions connect to it as the model's identities, each with its certificate from
``rap certs``. Every attack is tried by a peer holding a real certificate of the system
(a stolen one, or a component that went rogue) that the model does not allow to do it,
and is shown refused: the message never reaches the session that would act on it, and the
router logs the refusal with the identity that tried. The same message from the identity
the model allows gets through (so a refusal is not a dead link). A peer without a
certificate cannot link at all.
"""

from __future__ import annotations

import json
from contextlib import AbstractAsyncContextManager
from pathlib import Path

import anyio
import pytest
from rap_cli.deploy import client_config
from rap_cli.testing import SecuredRouter, model_copy, secured_router
from rap_schemas import keys
from rap_sdk.errors import FabricError
from rap_sdk.fabric import (
    QueryRequest,
    Reply,
    ZenohConfig,
    ZenohFabric,
    node_overlay,
)

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh, pytest.mark.timeout(120)]

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "examples/lidar_occlusion/model.yaml"
S = "demo"
SPIN = keys.data(S, "tb1/spin_config")
VERDICT = keys.event(S, "verdict")
LIDAR_MASK = keys.kb(S, "lidar_mask")
HANDLING = keys.kb(S, "handling_anomaly")
MODEL_STORE = keys.kb(S, "_models/occlusion")
KB_ALIVE = keys.alive(S, "knowledge")


def _bed(tmp_path: Path) -> AbstractAsyncContextManager[SecuredRouter]:
    return secured_router(model_copy(MODEL, tmp_path), tmp_path)


async def _arrives(sub: object, fabric: ZenohFabric, key: str, payload: bytes) -> bool:
    """Whether ``payload`` put on ``key`` by ``fabric`` reaches subscription ``sub``
    (retried for 2 s: a first put may go out before the route is known)."""
    with anyio.move_on_after(2):
        while True:
            await fabric.publish(key, payload)
            with anyio.move_on_after(0.2):
                while True:
                    got = await sub.get()  # type: ignore[attr-defined]
                    if got.payload == payload:
                        return True
    return False


async def test_attacks_are_refused_and_logged_with_the_identity(tmp_path: Path) -> None:
    async with (
        _bed(tmp_path) as bed,
        bed.session("ops") as ops,
        bed.session("robot.robot") as sim,
        bed.session("robot.runner") as robot_runner,
        bed.session("edge.runner") as edge_runner,
        bed.session("edge.knowledge") as kb,
        bed.session("edge.manager") as manager,
    ):
        # 1. a plan published straight on the robot's spin_config: only the executor's
        # process may; the simulator's own identity may not (it only takes plans)
        plans = sim.subscribe(SPIN)
        assert not await _arrives(plans, manager, SPIN, b"50 rad/s from the manager")
        await bed.refusal("edge.manager", "put", SPIN)
        assert await _arrives(plans, robot_runner, SPIN, b"the executor's plan")

        # 2. an approval sealed as "legitimate" by another process: only the process
        # that hosts the Legitimate stage may put a verdict
        verdicts = robot_runner.subscribe(VERDICT)
        forged = b'{"source": "legitimate", "approved": true, "spin": 50.0}'
        assert not await _arrives(verdicts, sim, VERDICT, forged)
        await bed.refusal("robot.robot", "put", VERDICT)
        assert await _arrives(verdicts, edge_runner, VERDICT, b"legitimate's verdict")

        # 3. knowledge written as the analysis by the robot's runner: it may write only
        # its components' keys (handling_anomaly), not the analysis' lidar_mask
        stream = kb.subscribe(keys.pattern(S, keys.Kind.KB))
        assert not await _arrives(stream, robot_runner, LIDAR_MASK, b"all clear")
        await bed.refusal("robot.runner", "put", LIDAR_MASK)
        assert await _arrives(stream, robot_runner, HANDLING, b"executor's write")

        # 4. a model stored and pinned: reserved knowledge keys are operators' only
        asked: list[str] = []

        async def answer(query: QueryRequest) -> list[Reply]:
            asked.append(query.key)
            return []

        served = kb.serve(keys.pattern(S, keys.Kind.KB), answer)
        try:
            with anyio.move_on_after(2):
                await edge_runner.query(MODEL_STORE, b"store and pin", timeout=1)
            await bed.refusal("edge.runner", "query", MODEL_STORE)
            assert asked == []
            with anyio.fail_after(10):
                while not asked:
                    await ops.query(MODEL_STORE, b"an operator's model", timeout=1)
            assert asked[0] == MODEL_STORE
        finally:
            served.undeclare()

        # 5. an admin verb (a swap) called by a process: operators only; the manager
        # may poll status and nothing else
        calls: list[str] = []

        async def admin(query: QueryRequest) -> list[Reply]:
            calls.append(query.key)
            return []

        swap = keys.admin(S, "analysis", "swap")
        served = edge_runner.serve(keys.pattern(S, keys.Kind.ADMIN, "analysis/*"), admin)
        try:
            with anyio.move_on_after(2):
                await manager.query(swap, b"evil:node", timeout=1)
            await bed.refusal("edge.manager", "query", swap)
            assert calls == []
            status = keys.admin(S, "analysis", "status")
            with anyio.fail_after(10):
                while status not in calls:
                    await manager.query(status, b"", timeout=1)
            with anyio.fail_after(10):
                while swap not in calls:
                    await ops.query(swap, b"an operator's swap", timeout=1)
        finally:
            served.undeclare()

        # 6. the knowledge service's liveliness token faked by another process
        sim.declare_token(KB_ALIVE)
        await bed.refusal("robot.robot", "liveliness token", KB_ALIVE)
        await anyio.sleep(0.5)
        assert await ops.alive(KB_ALIVE) == []
        kb.declare_token(KB_ALIVE)
        for _ in range(100):  # within about 10 s
            if await ops.alive(KB_ALIVE):
                break
            await anyio.sleep(0.1)
        else:
            raise AssertionError("the knowledge identity's own token never showed")


async def test_a_peer_without_a_certificate_cannot_link(tmp_path: Path) -> None:
    async with _bed(tmp_path) as bed:
        # plain TCP to the TLS port, and TLS without a certificate: no link
        bare = client_config(bed.endpoint, secure=True)
        plain = ZenohConfig(mode="client", listen=[], connect=[bed.endpoint.replace("tls", "tcp")])
        for conf in (ZenohConfig(mode="client", listen=[], connect=[bed.endpoint], extra=bare),):
            with pytest.raises(FabricError, match="Unable to connect"):
                async with ZenohFabric(conf):
                    pass
        with pytest.raises(FabricError, match="Unable to connect"):
            async with ZenohFabric(plain):
                pass
        # a RAP process without an identity is told what to set
        with pytest.raises(FabricError, match="RAP_AS"):
            node_overlay(ZenohConfig(), json.dumps(bare), env={})
