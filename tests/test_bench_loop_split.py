"""The no-knowledge chain of ``bench.loop.split`` closes the loop as the race's chain
does, with no knowledge read or written."""

from __future__ import annotations

import anyio
from rap_sdk import MemoryFabric, NodeRuntime, run_nodes

from bench.loop import chain_bare
from bench.loop.rap import PLANS, Robot, _round
from bench.loop.split import ratios


def test_the_bare_plans_deploy_the_bare_chain() -> None:
    for variant in ("rap-1proc-bare", "rap-5proc-bare"):
        assert "bench.loop.chain_bare:" in PLANS[variant].read_text()
        assert "bench.loop.chain:" not in PLANS[variant].read_text()


def test_the_bare_chain_answers_every_scan_without_knowledge() -> None:
    nodes = [
        chain_bare.monitor,
        chain_bare.analysis,
        chain_bare.planner,
        chain_bare.legitimator,
        chain_bare.executor,
    ]

    async def main() -> None:
        robot = Robot()
        async with MemoryFabric() as fabric, run_nodes(nodes, fabric=fabric, system="race") as rts:
            rt = NodeRuntime(robot.node, fabric=fabric, system="race", trace=False)
            async with anyio.create_task_group() as tg:
                await tg.start(rt.run)
                res = await _round(rt, robot, 200.0, 5)
                rt.stop()
            assert res["lost"] == 0
            assert res["received"] == 5
            for name in ("monitor", "analysis", "planner"):
                kb = rts[name].knowledge
                assert not kb._replicas  # nothing read
                assert not kb._own  # nothing written

    anyio.run(main)


def test_ratios_leave_missing_rows_out() -> None:
    assert ratios({"a": 2.0, "b": 1.0, "c": None}, "b") == {"a": 2.0, "b": 1.0, "c": None}
