"""``rap export aadl``: the AADL it writes parses with no finding, and ``rap import aadl``
reads it back to the same model (a round-trip property over generated models)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rap_cli.aadl import parse_aadl
from rap_cli.app import app
from rap_cli.exporters.aadl import export_aadl
from rap_cli.exporters.aadl_names import RESERVED, Names, ident
from rap_cli.importers.aadl import import_aadl
from rap_schemas import DeploymentPlan, load_plan
from typer.testing import CliRunner

REPO = Path(__file__).resolve().parents[3]
LIDAR = REPO / "examples/lidar_occlusion/model.yaml"
runner = CliRunner()

_name = st.from_regex(r"[a-z][a-z0-9]{0,6}([_-][a-z0-9]{1,3})?", fullmatch=True)
_SCALARS = ["bool", "int", "int8", "uint16", "int64", "float", "float32", "float64", "str"]
_WIRE = ["rap.LaserScan/2", "rap.SpinPlan/1", "rap.Verdict/1"]
_RATES = [1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0]


@st.composite
def models(draw: st.DrawFn) -> DeploymentPlan:
    """A model that uses every part the export writes."""
    nodes = draw(st.lists(_name, min_size=1, max_size=3, unique=True))
    compute: dict[str, Any] = {}
    for n in nodes:
        compute[n] = {
            "address": draw(st.sampled_from([None, "127.0.0.1", "robot.local"])),
            "architecture": draw(st.sampled_from([None, "x86_64", "aarch64"])),
            "resources": draw(
                st.sampled_from([{}, {"cpus": 2.0}, {"cpus": 0.5, "memory_mb": 512}])
            ),
            "listen": draw(st.sampled_from([[], ["tcp/127.0.0.1:7447"]])),
            "doc": draw(st.sampled_from(["", 'the "edge" server'])),
        }
    enums = draw(st.lists(_name, max_size=1, unique=True))
    msg_names = draw(
        st.lists(_name, max_size=3, unique=True).filter(lambda m: not set(m) & set(enums))
    )
    messages: dict[str, Any] = {e: {"enum": ["A", "B_2"]} for e in enums}
    for i, m in enumerate(msg_names):
        earlier = msg_names[:i] + enums
        scalar = st.sampled_from(_SCALARS + earlier)
        ftype = st.one_of(
            scalar,
            scalar.map(lambda t: f"list[{t}]"),
            st.tuples(scalar, st.integers(1, 64)).map(lambda p: f"list[{p[0]}, {p[1]}]"),
            st.sampled_from(["optional[float]", "bytes"]),
        )
        fields = draw(st.dictionaries(_name, ftype, min_size=1, max_size=4))
        messages[m] = {
            "fields": {
                f: ({"type": t, "ge": 0.0} if t == "float" else {"type": t})
                for f, t in fields.items()
            },
            "doc": draw(st.sampled_from(["", "a message"])),
        }
    comps = draw(st.lists(_name, min_size=1, max_size=4, unique=True))
    stages = ["monitor", "analyse", "plan", "legitimate", "execute"]
    types = [None, *msg_names, *_WIRE]
    components: dict[str, Any] = {}
    for i, c in enumerate(comps):
        ports = draw(st.lists(_name, max_size=3, unique=True))
        spec: dict[str, Any] = {
            "node": draw(st.sampled_from(nodes)),
            "ports": {
                p: {
                    "direction": draw(st.sampled_from(["in", "out", "in-out"])),
                    "kind": kind,
                    "type": None if kind == "event" else draw(st.sampled_from(types)),
                    "topic": draw(st.sampled_from([None, "tb1/scan", "new-data"])),
                }
                for p in ports
                for kind in [draw(st.sampled_from(["event", "data", "event-data"]))]
            },
            "reads": draw(st.sampled_from([[], ["laser_scan"]])),
            "writes": draw(st.sampled_from([[], ["laser_scan", "mask"]])),
        }
        if draw(st.booleans()):
            spec["stage"] = stages[i % len(stages)]
            spec["module"] = f"pkg.nodes:{ident(c)}_{i}"
        else:
            spec["role"] = "managed"
            spec["external"] = True
        if draw(st.booleans()):
            spec["dispatch"] = {
                "kind": draw(st.sampled_from(["periodic", "sporadic"])),
                "rate_hz": draw(st.sampled_from([None, *_RATES])),
            }
        if draw(st.booleans()):
            modes = ["Initialise", "Wait", "Verify"]
            spec["modes"] = modes
            spec["threads"] = {
                "worker": {"in_modes": ["Wait", "Verify"]},
                "ticker": {"dispatch": {"kind": "periodic", "rate_hz": 10.0}},
            }
            triggers = [p for p, ps in spec["ports"].items() if ps["direction"] != "out"][:1]
            spec["mode_transitions"] = [
                {"from": "Initialise", "to": "Wait", "triggers": triggers},
                {"from": "Wait", "to": "Verify", "triggers": []},
            ]
        if draw(st.booleans()):
            spec["config"] = {"window": 3, "name": "x"}
        components[c] = spec
    ends = [(c, p, ps) for c, spec in components.items() for p, ps in spec["ports"].items()]
    outs = [f"{c}.{p}" for c, p, ps in ends if ps["direction"] != "in"]
    ins = [f"{c}.{p}" for c, p, ps in ends if ps["direction"] != "out"]
    buses = {"lan": {"nodes": nodes}} if draw(st.booleans()) else {}
    connections = []
    if outs and ins:
        for k in range(draw(st.integers(0, 3))):
            conn: dict[str, Any] = {
                "from": draw(st.sampled_from(outs)),
                "to": draw(st.sampled_from(ins)),
                "name": f"c{k + 1}" if draw(st.booleans()) else None,
            }
            if buses and draw(st.booleans()):
                conn["bus"] = "lan"
            connections.append(conn)
    data = {
        "system": draw(_name),
        "doc": "generated",
        "compute_nodes": compute,
        "buses": buses,
        "messages": messages,
        "components": components,
        "connections": connections,
        "knowledge": draw(
            st.sampled_from(
                [
                    {"backend": "memory", "node": nodes[0]},
                    {"backend": "redis", "url": "redis://127.0.0.1:6379/0"},
                    {"backend": "sqlite", "path": "kb.sqlite"},
                ]
            )
        ),
        "trust": {"node": nodes[-1], "specs": ["specs/order.dsrv"]},
        "fabric": {"mode": draw(st.sampled_from(["peer", "client"])), "routers": []},
    }
    return msgspec.convert(data, DeploymentPlan)


def _without_origins(value: Any) -> Any:
    """The model with every ``origin`` cleared (the import says where parts came from)."""
    data = msgspec.to_builtins(value)

    def strip(x: Any) -> Any:
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k != "origin"}
        if isinstance(x, list):
            return [strip(v) for v in x]
        return x

    return strip(data)


def _round_trip(plan: DeploymentPlan, tmp: Path) -> tuple[DeploymentPlan | None, list[str]]:
    exported = export_aadl(plan)
    paths = []
    for name, text in exported.files.items():
        path = tmp / name
        path.write_text(text, encoding="utf-8")
        paths.append(path)
    imported = import_aadl(paths, root=exported.root)
    return imported.plan, [str(d) for d in imported.diagnostics if d.severity != "note"]


def test_the_exported_lidar_model_parses_cleanly() -> None:
    plan = load_plan(LIDAR).plan
    for name, text in export_aadl(plan).files.items():
        _, diagnostics = parse_aadl(text, name)
        assert diagnostics == [], [str(d) for d in diagnostics]


def test_the_lidar_model_round_trips(tmp_path: Path) -> None:
    plan = load_plan(LIDAR).plan
    back, problems = _round_trip(plan, tmp_path)
    assert problems == []
    assert back is not None
    assert _without_origins(back) == _without_origins(plan)


@settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(plan=models())
def test_export_then_import_gives_the_same_model(plan: DeploymentPlan, tmp_path: Path) -> None:
    folder = Path(tempfile.mkdtemp(dir=tmp_path))  # hypothesis reuses tmp_path
    back, problems = _round_trip(plan, folder)
    assert problems == []
    assert back is not None
    assert _without_origins(back) == _without_origins(plan)


@pytest.mark.parametrize("name", ["robot-1", "data", "9lives", "a__b_", "tb1/scan", "Port"])
def test_identifiers_are_valid_aadl(name: str) -> None:
    made = ident(name)
    assert made[0].isalpha()
    assert "__" not in made
    assert not made.endswith("_")
    assert made.lower() not in RESERVED


def test_names_stay_unique_in_a_scope() -> None:
    names = Names(("Software",))
    assert names("a-b") == "a_b"
    assert names("a_b") == "a_b_2"
    assert names("software") == "software_2"
    assert names("a-b") == "a_b"


def test_rap_export_aadl_writes_the_folder_and_refuses_a_wrong_model(tmp_path: Path) -> None:
    res = runner.invoke(app, ["export", "aadl", str(LIDAR), "-o", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "RAP.aadl",
        "demo.aadl",
        "demo_logical.aadl",
        "demo_messages.aadl",
        "demo_physical.aadl",
    ]
    bad = tmp_path / "bad.yaml"
    bad.write_text(LIDAR.read_text().replace("node: edge\n", "node: nowhere\n", 1))
    res = runner.invoke(app, ["export", "aadl", str(bad), "-o", str(tmp_path / "bad")])
    assert res.exit_code == 1
    assert not (tmp_path / "bad").exists()
