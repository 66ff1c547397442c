"""The golden suite: every case in golden/*.yaml, run through the parser, the static
checks, the monitor and the trace-file reader.

A case is ``{name, spec, trace, expect}`` (the console lines, drain included),
``{name, spec, error}`` (a spec that must be rejected; ``error`` is a substring of the
message), or ``{name, spec, trace, error[, expect]}`` (a run-time or input error, after
the lines in ``expect``). The expectations were derived by hand from
docs/trust_checker.md, not by running the code.
"""

from __future__ import annotations

import pathlib
from typing import Any

import pytest
import yaml
from trust_checker.engine import SpecRunner
from trust_checker.errors import SpecError, TrustError
from trust_checker.lang import load_spec
from trust_checker.tracefile import read_trace, run_trace
from trust_checker.values import console

GOLDEN = pathlib.Path(__file__).parent / "golden"
_KEYS = {"name", "spec", "trace", "expect", "error"}


def _cases() -> list[dict[str, Any]]:
    cases: list[dict[str, Any]] = []
    for f in sorted(GOLDEN.glob("*.yaml")):
        for case in yaml.safe_load(f.read_text(encoding="utf-8")):
            case["file"] = f.name
            cases.append(case)
    return cases


CASES = _cases()


def _lines(block: str | None) -> list[str]:
    return [ln.strip() for ln in (block or "").splitlines() if ln.strip()]


def test_the_suite_is_well_formed() -> None:
    names = [c["name"] for c in CASES]
    assert len(names) >= 60
    assert len(set(names)) == len(names), "case names must be unique"
    for c in CASES:
        assert set(c) - {"file"} <= _KEYS, c["name"]
        assert "spec" in c, c["name"]
        assert ("expect" in c) or ("error" in c), c["name"]
        if "error" not in c:
            assert "trace" in c, c["name"]


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_golden(case: dict[str, Any]) -> None:
    name = case["name"]
    if "trace" not in case:  # a spec that must be rejected
        with pytest.raises(SpecError) as rejected:
            load_spec(case["spec"], path=f"{name}.dsrv")
        assert case["error"] in str(rejected.value)
        return
    spec = load_spec(case["spec"], path=f"{name}.dsrv")
    ticks = read_trace(case["trace"], path=f"{name}.trace")
    if "error" not in case:
        assert run_trace(spec, ticks) == _lines(case["expect"])
        return
    got: list[str] = []
    with pytest.raises(TrustError) as err:
        _run_collecting(SpecRunner(spec), ticks, got)
    assert case["error"] in str(err.value)
    assert got == _lines(case.get("expect"))


def _run_collecting(m: SpecRunner, ticks: list[dict[str, object]], got: list[str]) -> None:
    """Like run_trace, but the lines printed before an error stay in ``got``."""
    for t in ticks:
        got += [f"{o.stream}[{o.tick}] = {console(o.value)}" for o in m.step(t)]
    got += [f"{o.stream}[{o.tick}] = {console(o.value)}" for o in m.finish()]
