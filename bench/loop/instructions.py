"""CPU work per loop cycle, counted in instructions under callgrind (no drift with load).

    python -m bench.loop.instructions [--cycles 300] [--kinds direct chain ...]

Children (three by default), each run twice under ``valgrind --tool=callgrind`` with
``N`` and ``2N`` cycles after the same warm-up; the difference of the two totals divided
by ``N`` is the cost of one cycle, with start-up, imports and warm-up cancelled out
(after the warm-up the heap is collected and frozen and collection is off: see
``_settle``):

- ``direct``: the five handlers of the race's chain called directly on a dict
  (``chain.handlers``): what the loop's own logic costs;
- ``chain``: the robot, the five nodes and the knowledge service in one process on the
  in-memory fabric, one scan at a time (send, wait for the plan): what RAP adds;
- ``chain-traced``: the same with a subscriber to every trace record (as a trust checker
  or a cycle tracker in the process would be);
- ``contract``: the contract floor (bench/loop/contract.py): the five stages as
  coroutines awaited one after another with the envelopes, knowledge versions, history
  and gate that RAP's contract asks for, and no dispatch at all;
- ``chain-no-knowledge``, ``chain-no-store`` (asked for with ``--kinds``: where the time
  goes): the chain with the handlers' knowledge on a dict, and with a knowledge service
  that stores nothing.

The children run on uvloop, as RAP's processes do. Results: instructions per cycle, and
the ratio of each chain to ``direct``.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import anyio
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_schemas import SpinPlan, keys
from rap_sdk import Context, MemoryFabric, Node, NodeRuntime, run_nodes

from bench.loop import chain
from bench.loop.chain import handlers
from bench.loop.contract import contract_cycle
from bench.loop.rap import SYSTEM, make_scan

WARMUP = 50
KINDS = ["direct", "contract", "chain", "chain-traced", "chain-no-knowledge", "chain-no-store"]
ROOT = Path(__file__).resolve().parents[2]


def _child(kind: str, cycles: int) -> None:
    """Run ``WARMUP + cycles`` cycles of ``kind`` and exit."""
    scan = make_scan()
    if kind == "direct":
        cycle = handlers(time.time_ns)
        for i in range(WARMUP + cycles):
            if i == WARMUP:
                _settle()
            assert cycle(scan) is not None
        return
    if kind == "contract":
        anyio.run(_contract, cycles, backend_options={"use_uvloop": True})
        return
    if kind == "chain-no-knowledge":
        _no_knowledge()
    elif kind == "chain-no-store":
        _no_store()
    anyio.run(_chain, kind == "chain-traced", cycles, backend_options={"use_uvloop": True})


def _no_knowledge() -> None:
    """Where the time goes: handlers' reads and writes on a dict instead of knowledge
    (no record, no stream, no service, no replica; the envelopes carry no versions)."""
    from rap_sdk import ContextKnowledge

    values: dict[str, Any] = {}

    async def write(self: ContextKnowledge, key: str, value: Any, **_: Any) -> int:
        values[key] = value
        return 1

    async def read(self: ContextKnowledge, key: str, type: Any = None, **_: Any) -> Any:
        return values[key]

    ContextKnowledge.write = write  # type: ignore[method-assign,assignment]
    ContextKnowledge.read = read  # type: ignore[method-assign,assignment]


def _no_store() -> None:
    """Where the time goes: the knowledge service takes the records written and stores
    nothing (everything else as in ``chain``)."""
    from knowledge.adapters.memory import MemoryStore
    from knowledge.ports import Applied
    from rap_schemas import KbRecord

    def apply_now(self: MemoryStore, rec: KbRecord, **_: Any) -> Applied:
        return Applied(rec.version, True)

    MemoryStore.apply_now = apply_now  # type: ignore[method-assign]


def _settle() -> None:
    """After the warm-up: what start-up left is collected and frozen, and collection
    stays off for the counted cycles, in every kind alike. A collection's cost depends
    on what has piled up (the gate remembers 4,096 plans, the knowledge history 1,000
    records a key), so with it on the count per cycle grows with ``N`` and the
    difference of two runs swings by millions of instructions. RAP's runners collect
    when idle instead (``rap_sdk.gc``); what that costs shows in the paced rows' p99."""
    gc.collect()
    gc.freeze()
    gc.disable()


async def _contract(cycles: int) -> None:
    scan = make_scan()
    cycle = contract_cycle()
    for i in range(WARMUP + cycles):
        if i == WARMUP:
            _settle()
        assert await cycle(scan) is not None


class _Robot:
    """Sends a scan and waits for the plan it causes (a bare future: the harness's own
    waiting is not what is measured)."""

    def __init__(self) -> None:
        self.node = Node("robot")
        self.got: asyncio.Future[None] | None = None

        @self.node.on_data(f"{chain.ROBOT}/spin_config")
        async def plan(ctx: Context, p: SpinPlan) -> None:
            if self.got is not None and not self.got.done():
                self.got.set_result(None)


async def _chain(traced: bool, cycles: int) -> None:
    nodes = [chain.monitor, chain.analysis, chain.planner, chain.legitimator, chain.executor]
    robot = _Robot()
    scan = make_scan()
    key = keys.data(SYSTEM, f"{chain.ROBOT}/scan")
    async with (
        MemoryFabric() as fabric,
        open_service(KnowledgeConfig(system=SYSTEM), fabric=fabric),
        run_nodes(nodes, fabric=fabric, system=SYSTEM),
        anyio.create_task_group() as tg,
    ):
        if traced:
            sub = fabric.subscribe(keys.pattern(SYSTEM, keys.Kind.TRACE))

            async def drain() -> None:
                async for _ in sub:
                    pass

            tg.start_soon(drain)
        rt = NodeRuntime(robot.node, fabric=fabric, system=SYSTEM, trace=False)
        await tg.start(rt.run)
        loop = asyncio.get_running_loop()
        with anyio.fail_after(30 + (WARMUP + cycles) * 0.5):  # one bound for the run
            for i in range(WARMUP + cycles):
                if i == WARMUP:
                    _settle()
                got = robot.got = loop.create_future()
                await rt.send(key, scan)
                # the loop turns once a cycle either way (the knowledge service and a
                # trace subscriber run): in one process the cycle may close inside send
                await (got if not got.done() else asyncio.sleep(0))
        rt.stop()
        tg.cancel_scope.cancel()


_TOTAL = re.compile(r"^(?:summary|totals):\s+(\d+)", re.MULTILINE)


def _instructions(kind: str, cycles: int) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "callgrind.out"
        # one thread: numpy's BLAS pool otherwise starts threads whose instructions
        # count by wall time, not by cycle (the two runs' difference then drifts)
        env = {
            **os.environ,
            "PYTHONHASHSEED": "0",
            "RERUN_ANALYTICS": "0",
            "OPENBLAS_NUM_THREADS": "1",
            "OMP_NUM_THREADS": "1",
        }
        subprocess.run(
            [
                "valgrind",
                "--tool=callgrind",
                f"--callgrind-out-file={out}",
                sys.executable,
                "-m",
                "bench.loop.instructions",
                "--child",
                kind,
                "--cycles",
                str(cycles),
            ],
            cwd=ROOT,
            env=env,
            check=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        found = _TOTAL.search(out.read_text(errors="replace"))
        if found is None:
            raise RuntimeError(f"no instruction total in callgrind's output for {kind}")
        return int(found.group(1))


def measure(
    cycles: int = 300, kinds: tuple[str, ...] = ("direct", "contract", "chain", "chain-traced")
) -> dict[str, Any]:
    """Instructions per cycle of each kind (and its ratio to ``direct``)."""
    if shutil.which("valgrind") is None:
        raise RuntimeError("valgrind is not installed (apt-get install valgrind)")
    out: dict[str, Any] = {"cycles": cycles, "warmup": WARMUP}
    for kind in kinds:
        one, two = _instructions(kind, cycles), _instructions(kind, 2 * cycles)
        out[kind] = round((two - one) / cycles)
        print(f"  {kind}: {out[kind]:,} instructions per cycle", file=sys.stderr, flush=True)
    direct = out.get("direct")
    for kind in kinds:
        if direct and kind != "direct":
            out[f"{kind}_vs_direct"] = round(out[kind] / direct, 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.loop.instructions", description=__doc__)
    ap.add_argument("--cycles", type=int, default=300)
    ap.add_argument("--child", choices=KINDS)
    ap.add_argument(
        "--kinds",
        nargs="+",
        choices=KINDS,
        default=["direct", "contract", "chain", "chain-traced"],
        help="what to count (chain-no-knowledge, chain-no-store: where the time goes)",
    )
    a = ap.parse_args()
    if a.child:
        _child(a.child, a.cycles)
        return
    print(measure(a.cycles, tuple(a.kinds)))


if __name__ == "__main__":
    main()
