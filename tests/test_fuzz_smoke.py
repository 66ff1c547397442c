"""bench/fuzz cannot rot: its mutations are reproducible and each one yields bytes, and a
small run against the real processes sends every target its samples, reads the
rejections and measures every process.

The small run checks the harness, not the loop: what it finds (crashes, a loop that does
not close) is the full run's business (``make fuzz``), so it is only reported here."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import anyio
import msgspec
import numpy as np
import pytest
from lidar_occlusion.analysis import to_message
from lidar_occlusion.demo import default_plan_path
from lidar_occlusion.scans import BEAMS, occluded_scan
from rap_schemas import LaserScan

from bench.fuzz.__main__ import render
from bench.fuzz.mutate import MUTATIONS, Mutator
from bench.fuzz.run import Options, run
from bench.fuzz.samples import plain

SYSTEM = "demo"


NOW = 1_700_000_000_000_000_000


def _batch(seed: int) -> list[tuple[str, bytes, bytes]]:
    """(mutation, the valid sample, the mutated one) for every mutation, three times."""
    m = Mutator(
        "data/tb1/scan",
        seed,
        sources=["fuzzer", "monitor"],
        ctx_keys=["laser_scan"],
        clock=lambda: NOW,
    )
    body = plain(occluded_scan(-0.4, 0.8))
    out = []
    for name in MUTATIONS * 3:
        valid = m.envelope("rap/demo/data/tb1/scan", LaserScan.TYPE, body)
        valid["uid"] = bytes(16)  # uids follow the clock's sub-ms counter: pinned here
        out.append((name, msgspec.msgpack.encode(valid), m.mutate(name, valid)))
    return out


def test_mutations_are_reproducible_and_each_one_changes_the_sample() -> None:
    a = _batch(7)
    assert a == _batch(7)
    assert a != _batch(8)
    assert {name for name, _, _ in a} == set(MUTATIONS)
    for name, valid, payload in a:
        assert isinstance(payload, bytes), name
        assert payload != valid, name


def test_nonfinite_floats_reach_the_wire() -> None:
    m = Mutator("t", 3)
    valid = m.envelope("k", LaserScan.TYPE, plain(occluded_scan()))
    seen, in_ranges = set(), set()
    for _ in range(20):
        env = msgspec.msgpack.decode(m.mutate("nonfinite", valid))
        body = env["body"]
        values = [body[k] for k in ("angle_min", "angle_increment", "range_min", "range_max")]
        ranges = list(memoryview(body["ranges"]).cast("f"))  # packed float32
        values += ranges
        seen |= {repr(v) for v in values if isinstance(v, float) and not math.isfinite(v)}
        in_ranges |= {repr(v) for v in ranges if not math.isfinite(v)}
    assert {"nan", "inf", "-inf"} <= seen
    assert {"nan", "-inf"} <= in_ranges  # beams of the packed ranges too


@pytest.mark.parametrize(
    ("msg", "expected"),
    [
        pytest.param(
            occluded_scan(-0.4, 0.8),
            [
                r"^ranges\[\d+\] is (nan|-inf|-1\.0|-1\.4\d*e-45);",  # a beam planted
                r"^ranges holds \d+ bytes, not a whole number of float32 beams",  # cut, grown
                r"^Expected `bytes`, got `array` - at `\$\.ranges`$",  # a list, as in /1
            ],
            id="scan",
        ),
        pytest.param(
            to_message(np.arange(BEAMS) % 7 == 0, occluded_scan()),
            [
                r"^occluded\[\d+\] is byte \d+;",  # a flag byte over 1
                r"^Expected `bytes`, got `array` - at `\$\.occluded`$",
            ],
            id="mask",
        ),
    ],
)
def test_packed_arrays_are_damaged_in_every_way(msg: Any, expected: list[str]) -> None:
    """``packed`` breaks a scan's float32 ranges and a mask's flags; the schema refuses
    what it makes (or reads it as another beam count), and nothing else escapes."""
    m = Mutator("t", 5)
    valid = m.envelope("k", msg.TYPE, plain(msg))
    reasons = []
    for _ in range(200):
        payload = m.mutate("packed", valid)
        assert payload != msgspec.msgpack.encode(valid)
        body = msgspec.msgpack.encode(msgspec.msgpack.decode(payload)["body"])
        try:
            msgspec.msgpack.decode(body, type=type(msg))
        except msgspec.ValidationError as exc:
            reasons.append(str(exc))
    for pattern in expected:
        assert any(re.search(pattern, r) for r in reasons), (pattern, sorted(set(reasons)))


@pytest.mark.slow
@pytest.mark.zenoh
@pytest.mark.timeout(180)
def test_a_small_fuzz_run_reaches_every_target_and_measures_every_process(
    tmp_path: Path,
) -> None:
    opts = Options(
        plan=default_plan_path("demo"),
        seconds=8.0,
        samples=1500,
        seed=1,
        specs=["stage_order"],
        logs=tmp_path / "logs",
        close_timeout=20.0,
    )
    report = anyio.run(run, opts)
    json.dumps(report, default=str)  # what __main__ writes
    assert report["system"] == SYSTEM
    assert report["warm_up"]["closed"]
    assert report["warm_up"]["checkers_heard"] == ["trust_stage_order"]
    targets = report["targets"]
    names = set(targets)
    # derived from the nodes' routes and the warm-up cycle's knowledge accesses
    assert {
        "data/tb1/scan",
        "event/new-data",
        "event/anomaly",
        "event/new-plan",
        "event/verdict",
        "event/plan-rejected",
        "kb/laser_scan",
        "kb/lidar_mask",
        "kb/planned_lidar_mask",
        "kb/handling_anomaly",
        "kb/fuzz/other",
        "trace/*",
        "kb/** (queries)",
        "admin/trust_stage_order/swap (queries)",
    } <= names
    assert all(t["sent"] >= 1500 for t in targets.values()), targets
    assert report["target_reached"]
    assert report["samples_total"] >= 1500 * len(targets)
    queries = targets["kb/** (queries)"]["replies"]
    assert sum(queries.values()) == targets["kb/** (queries)"]["sent"]
    assert report["rejections"]["records"] > 0
    assert report["rejections"]["by_reason"]
    assert set(report["processes"]) == {
        "knowledge",
        "runner-robot",
        "runner-edge",
        "trust_stage_order",
    }
    for name, p in report["processes"].items():
        assert p["rss_before_kib"] > 0, name
        assert p["exit_code"] is not None, name
    assert isinstance(report["crashes"], list)
    assert isinstance(report["loop_closed_after"], bool)
    text = render(report, {"cpu": "x", "cores": 1, "mem_gib": 1, "python": "3", "os": "x",
                           "packages": {}, "date": "now"})  # fmt: skip
    assert "rejections by reason" in text
    assert "loop closed after the flood" in text
