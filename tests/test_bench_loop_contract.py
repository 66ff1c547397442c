"""The contract floor of the loop race does the contract's work: every cycle ends in the
plan, knowledge versions grow and are kept in history, and a read refuses a replica
behind the version its trigger names."""

from __future__ import annotations

import anyio
import pytest
from rap_sdk.knowledge import HybridClock

from bench.loop.chain import PLAN
from bench.loop.contract import HISTORY, _Store, contract_cycle
from bench.loop.rap import make_scan, run_contract_paced


def test_every_cycle_ends_in_the_plan() -> None:
    async def main() -> None:
        cycle = contract_cycle()
        scan = make_scan()
        for _ in range(3):
            assert await cycle(scan) == PLAN

    anyio.run(main)


def test_writes_are_versioned_and_kept_and_reads_are_causal() -> None:
    kb, clock = _Store(), HybridClock("w")
    versions = [kb.write(clock, "w", "k", i) for i in range(HISTORY + 5)]
    assert versions == sorted(set(versions))
    assert len(kb.history["k"]) == HISTORY
    assert kb.read(clock, "k", versions[-1]) == HISTORY + 4
    with pytest.raises(LookupError, match="behind"):
        kb.read(clock, "k", versions[-1] + 1)


def test_the_paced_row_measures_every_cycle() -> None:
    r = anyio.run(run_contract_paced, 200.0, 5, 2)
    assert len(r["latencies_ns"]) == 5
    assert all(ns > 0 for ns in r["latencies_ns"])
