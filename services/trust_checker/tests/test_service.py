"""open_service: what it wires, what it refuses (the transports are tested through it in
test_io_mqtt.py, test_io_fabric.py, test_hardening.py)."""

from __future__ import annotations

import json

import msgspec
import pytest
from rap_sdk import ConfigError, MemoryFabric
from trust_checker.config import FabricConfig, ServiceConfig
from trust_checker.console import ConsoleSink
from trust_checker.engine import SpecRunner
from trust_checker.errors import SpecError
from trust_checker.io.specs import MAX_SPEC_CHARS, load_text
from trust_checker.io.ticks import Arrival, TickPolicy
from trust_checker.operators import MAX_ENTRIES
from trust_checker.service import open_service

from services.trust_checker.tests.io_support import FakeRunner, FakeSpec, fake_loader

pytestmark = pytest.mark.anyio

SPEC = "in x: Float\nout ok: Bool\nok = x < 2.0\n"


async def test_the_spec_runs_and_a_running_sink_is_started_and_drained(
    capsys: pytest.CaptureFixture[str],
) -> None:
    async with open_service(
        ServiceConfig(), load_text(SPEC), sinks=[ConsoleSink(explain=True)]
    ) as s:
        assert isinstance(s.runner, SpecRunner)
        assert (s.mqtt, s.fabric) == (None, None)
        for i, x in enumerate((1.0, 3.0)):
            await s.session.submit(Arrival({"x": x}, 1_000 + i, "test"))
        await s.session.wait_idle()
    captured = capsys.readouterr()
    assert captured.out == "ok[0] = Bool(true)\nok[1] = Bool(false)\n"
    (verdict,) = [json.loads(line) for line in captured.err.splitlines()]
    assert (verdict["stream"], verdict["tick"], verdict["value"]) == ("ok", 1, False)
    assert s.summary().startswith("2 ticks: 2 outputs, 1 verdicts, 0 rejected")


async def test_a_runner_of_ones_own_gives_no_verdicts() -> None:
    runner = FakeRunner(FakeSpec(("a",), ("s",)))
    async with open_service(ServiceConfig(node="n1"), runner, loader=fake_loader) as s:
        assert s.runner is runner
        assert s.session.explainer is None
        assert s.session.node == "n1"


async def test_a_fabric_and_its_config_go_together() -> None:
    spec = load_text(SPEC)
    with_fabric = ServiceConfig(fabric=FabricConfig(system="s"))
    with pytest.raises(ConfigError, match=r"config\.fabric is set .* - pass fabric=") as err:
        async with open_service(with_fabric, spec):
            pass
    assert "system 's'" in str(err.value)
    async with MemoryFabric() as fabric:
        with pytest.raises(ConfigError, match=r"config\.fabric is None - set config\.fabric="):
            async with open_service(ServiceConfig(), spec, fabric=fabric):
                pass


def test_the_tick_policy_is_checked_when_the_config_is_built() -> None:
    assert ServiceConfig(tick="window:10ms").policy == TickPolicy("window", 10_000_000)
    with pytest.raises(ValueError, match="unknown tick policy 'often' - use 'message'"):
        ServiceConfig(tick="often")
    with pytest.raises(msgspec.ValidationError, match="unknown tick policy"):
        msgspec.json.decode(b'{"tick": "often"}', type=ServiceConfig)
    with pytest.raises(msgspec.ValidationError, match="unknown field `nodes`"):
        msgspec.json.decode(b'{"nodes": "x"}', type=ServiceConfig)


async def test_a_spec_whose_values_grow_without_bound_does_not_stop_the_checker(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``y`` nests one list deeper every tick: past the depth limit its outputs are not
    given to the sinks (which convert them recursively), counted as evaluation errors,
    and the other outputs keep coming."""
    spec = load_text(
        "in x: Float\nout ok: Bool\nout y: List<Any>\nok = x < 2.0\ny = [default(y[1], [])]\n"
    )
    async with open_service(ServiceConfig(), spec, sinks=[ConsoleSink()]) as s:
        for i in range(1500):  # deeper than Python's own recursion limit
            await s.session.submit(Arrival({"x": 1.0}, 1_000 + i, "test"))
        await s.session.wait_idle()
    out = capsys.readouterr().out
    stats = s.session.stats
    assert stats.ticks + stats.eval_errors >= 1500  # every input was taken, none stopped it
    assert out.count("ok[") == stats.ticks  # ok came out at every tick that evaluated
    assert out.count("ok[") > 1000
    assert out.count("y[") < 100  # y only while it was shallow


async def test_a_map_that_grows_with_its_input_is_bounded() -> None:
    """make fuzz fed a map of every knowledge key seen with made-up keys: the checker
    copied an ever larger map at every tick and reached 13 GiB. Collections stop at
    MAX_ENTRIES: a tick that would grow one past it fails, the checker goes on."""
    spec = load_text(
        "in key: Str\nout n: Int\nout seen: Map<Bool>\n"
        "seen = Map.insert(default(seen[1], Map()), key, true)\nn = 1\n"
    )
    async with open_service(ServiceConfig(), spec) as s:
        for i in range(MAX_ENTRIES + 50):
            await s.session.submit(Arrival({"key": f"k{i}"}, 1_000 + i, "test"))
        await s.session.wait_idle()
        assert s.session.stats.eval_errors == 50
        assert s.session.stats.ticks == MAX_ENTRIES


def test_a_spec_text_over_the_limit_is_refused() -> None:
    with pytest.raises(SpecError, match="over the limit of"):
        load_text("out y: Int\ny = " + "1+" * (MAX_SPEC_CHARS // 2) + "1\n")
