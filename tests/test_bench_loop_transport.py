"""The loop race's transport floors come back, cycle for cycle (short rounds)."""

from __future__ import annotations

from bench.loop.transport import STAGES, zenoh_echo, zenoh_echo_loop, zenoh_relay


def test_the_relay_floor_crosses_every_stage_and_comes_back() -> None:
    r = zenoh_relay(50.0, 10, warmup=2)
    assert STAGES == 5
    assert (r["received"], r["lost"]) == (10, 0)
    assert all(ns > 0 for ns in r["latencies_ns"])


def test_the_echo_floor_comes_back() -> None:
    r = zenoh_echo(50.0, 10, warmup=2)
    assert (r["received"], r["lost"]) == (10, 0)


def test_the_loop_woken_echo_floor_comes_back() -> None:
    r = zenoh_echo_loop(50.0, 10, warmup=2)
    assert (r["received"], r["lost"]) == (10, 0)
    assert all(ns > 0 for ns in r["latencies_ns"])
