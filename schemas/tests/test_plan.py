"""Deployment plans: a good plan loads; each mistake is reported at its line with the bad
value and the fix; plans round-trip through YAML."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st
from rap_schemas import (
    ComponentSpec,
    ComputeNode,
    DeploymentPlan,
    KnowledgeSpec,
    PlanDocument,
    PlanError,
    Stage,
    load_plan,
    parse_plan,
)
from rap_schemas.export import PLAN_SCHEMA, render
from rap_schemas.limits import MAX_MESSAGE_BYTES

GOOD = """\
system: demo
compute_nodes:
  laptop:
    listen: ["tcp/127.0.0.1:7447"]
  robot:
    connect: ["tcp/127.0.0.1:7447"]
knowledge:
  backend: memory
  node: laptop
components:
  monitor:
    module: lidar_occlusion.nodes:monitor
    stage: monitor
    node: robot
  analysis:
    module: lidar_occlusion.nodes:analysis
    stage: analyse
    node: laptop
    config: {period: 2.0}
"""


def test_a_good_plan_loads_with_its_mapping() -> None:
    doc = parse_plan(GOOD, "p.yaml")
    plan = doc.plan
    assert plan.system == "demo"
    assert plan.compute_nodes["laptop"] == ComputeNode(listen=["tcp/127.0.0.1:7447"])
    assert plan.knowledge == KnowledgeSpec(backend="memory", node="laptop")
    assert plan.components_on("robot") == {
        "monitor": ComponentSpec(
            module="lidar_occlusion.nodes:monitor", stage=Stage.MONITOR, node="robot"
        )
    }
    assert plan.components["analysis"].config == {"period": 2.0}
    assert doc.where(("components", "analysis"), key=True) == "p.yaml:15:3"
    assert doc.where(("components", "analysis", "stage")) == "p.yaml:17:12"


def test_a_minimal_plan_takes_the_defaults() -> None:
    plan = parse_plan("system: s\ncompute_nodes: {one: {}}\n").plan
    assert plan.compute_nodes == {"one": ComputeNode()}
    assert plan.knowledge == KnowledgeSpec()
    assert plan.components == {}


@pytest.mark.parametrize(
    ("old", "new", "where", "words"),
    [
        ("system: demo", "system: de/mo", "p.yaml:1:9", ["invalid system 'de/mo'", "one"]),
        ("system: demo", "system: 12", "p.yaml:1:9", ["Expected `str`", "'12'", "quote"]),
        ("system: demo", "sistem: demo", "p.yaml:1:1", ["unknown field `sistem`", "`system`"]),
        ("  robot:\n", "  laptop:\n", "p.yaml:5:3", ["'laptop' appears twice", "line 3"]),
        ("  robot:\n", "  ro/bot:\n", "p.yaml:5:3", ["invalid compute node name 'ro/bot'"]),
        (
            '["tcp/127.0.0.1:7447"]\n  robot',
            '["127.0.0.1:7447"]\n  robot',
            "p.yaml:4:14",
            ["'127.0.0.1:7447' is not a Zenoh endpoint", "'tcp/127.0.0.1:7447'"],
        ),
        (
            'listen: ["tcp/127.0.0.1:7447"]',
            "listen: tcp/127.0.0.1:7447",
            "p.yaml:4:13",
            ["Expected `array`, got `str`", "$.compute_nodes.laptop.listen"],
        ),
        ("backend: memory", "backend: mongo", "p.yaml:8:12", ["'mongo'", "memory, redis"]),
        ("  node: laptop\ncomp", "  node: nas\ncomp", "p.yaml:9:9", ["'nas'", "laptop, robot"]),
        (
            "backend: memory",
            "backend: memory\n  url: redis://x",
            "p.yaml:9:8",
            ["knowledge.url is for the redis backend", "set backend: redis"],
        ),
        (
            "backend: memory",
            "backend: memcached\n  url: redis://x",
            "p.yaml:9:8",
            ["knowledge.url 'redis://x' is not a memcached URL", "memcached://HOST[:PORT]"],
        ),
        (
            "backend: memory",
            "backend: kafka\n  url: redis://x",
            "p.yaml:9:8",
            ["knowledge.url 'redis://x' is not a kafka URL", "kafka://HOST[:PORT]"],
        ),
        (
            "    stage: analyse",
            "    stage: analyze",
            "p.yaml:17:12",
            ["Invalid enum value 'analyze'", "$.components.analysis.stage", "analyse"],
        ),
        (
            "    node: laptop\n    config",
            "    node: lapptop\n    config",
            "p.yaml:18:11",
            ["compute node 'lapptop'", "not define", "laptop, robot"],
        ),
        (
            "    module: lidar_occlusion.nodes:analysis",
            "    modul: lidar_occlusion.nodes:analysis",
            "p.yaml:16:5",
            ["unknown field `modul`", "$.components.analysis", "did you mean `module`?"],
        ),
        (
            "    node: robot\n",
            "",
            "p.yaml:11:3",
            ["'monitor' is bound to no compute node", "add 'node: <name>'", "robot"],
        ),
        (
            "lidar_occlusion.nodes:analysis",
            "lidar_occlusion/nodes.py",
            "p.yaml:16:13",
            ["'lidar_occlusion/nodes.py' is not a 'package.module:attribute'", "e.g."],
        ),
        (
            "lidar_occlusion.nodes:analysis",
            "lidar_occlusion.nodes:monitor",
            "p.yaml:16:13",
            ["same Node as component 'monitor'"],
        ),
        ("  analysis:\n", "  ana/lysis:\n", "p.yaml:15:3", ["invalid component name"]),
        ("  analysis:\n", "  monitor:\n", "p.yaml:15:3", ["'monitor' appears twice"]),
        ("config: {period: 2.0}", "config: [2.0]", "p.yaml:19:13", ["Expected `object`"]),
        ("components:", "components: [\n", "p.yaml:", ["not valid YAML"]),
    ],
)
def test_each_mistake_names_its_line_the_value_and_the_fix(
    old: str, new: str, where: str, words: list[str]
) -> None:
    assert old in GOOD
    with pytest.raises(PlanError) as exc:
        parse_plan(GOOD.replace(old, new, 1), "p.yaml")
    message = str(exc.value)
    assert message.startswith(where + (":" if not where.endswith(":") else "")), message
    for word in words:
        assert word in message, message
    assert exc.value.source == "p.yaml"


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("", "p.yaml: the deployment plan is empty"),
        ("- a\n", "p.yaml:1:1: Expected `object`, got `array`"),
        ("system: s\ncompute_nodes: {}\n", "p.yaml:2:16: the plan defines no compute nodes"),
        ("system: s\n", "p.yaml:1:1: Object missing required field `compute_nodes`"),
        ("a: 1\n---\nb: 2\n", "p.yaml:2:1: not valid YAML: expected a single document"),
    ],
)
def test_whole_file_mistakes(text: str, words: str) -> None:
    with pytest.raises(PlanError, match="^" + words.replace("`", ".").replace("(", ".")):
        parse_plan(text, "p.yaml")


def test_the_sample_limit_defaults_to_what_rap_sends_and_takes_a_sane_value() -> None:
    assert parse_plan(GOOD).plan.fabric.max_sample_bytes == MAX_MESSAGE_BYTES == 257 << 20
    for value in (65536, 4 << 20, 1 << 30):
        text = GOOD + f"fabric:\n  max_sample_bytes: {value}\n"
        assert parse_plan(text).plan.fabric.max_sample_bytes == value


@pytest.mark.parametrize(
    ("value", "words"),
    [
        ("1000", ["is 1000: under 65536 (64 KiB)", "give at least 65536"]),
        ("-1", ["is -1: under 65536", "give at least 65536"]),
        ("65535", ["is 65535: under 65536", "never reassembled"]),
        ("1073741825", ["is 1073741825: over 1073741824 (1 GiB", "give at most 1073741824"]),
        ("4 MiB", ["Expected `int`, got `str`", "$.fabric.max_sample_bytes"]),
    ],
)
def test_a_silly_sample_limit_names_its_line_and_the_fix(value: str, words: list[str]) -> None:
    text = GOOD + f"fabric:\n  tls: false\n  max_sample_bytes: {value}\n"
    with pytest.raises(PlanError) as exc:
        parse_plan(text, "p.yaml")
    message = str(exc.value)
    assert message.startswith("p.yaml:22:21: "), message
    for word in words:
        assert word in message, message
    if "Expected" not in message:
        assert "leave it out for the default 269484032 (257 MiB)" in message


def test_a_plan_built_in_code_is_checked_with_paths() -> None:
    plan = DeploymentPlan(
        system="s",
        compute_nodes={"a": ComputeNode()},
        components={"m": ComponentSpec(module="x:m", stage=Stage.MONITOR, node="b")},
    )
    with pytest.raises(PlanError) as exc:
        PlanDocument.from_plan(plan, "code")
    assert str(exc.value).startswith("code: at `$.components.m.node`: component 'm'")


def test_load_plan_reads_a_file_and_names_a_missing_one(tmp_path: Path) -> None:
    path = tmp_path / "plan.yaml"
    path.write_text(GOOD, encoding="utf-8")
    assert load_plan(path).plan == parse_plan(GOOD).plan
    assert load_plan(path).source == str(path)
    with pytest.raises(PlanError, match=r"nope\.yaml: cannot read the deployment plan"):
        load_plan(tmp_path / "nope.yaml")


def test_the_plan_schema_is_exported_with_the_messages() -> None:
    schema = msgspec.json.decode(render()[PLAN_SCHEMA])
    assert schema["title"] == "rap.DeploymentPlan"
    plan = schema["$defs"]["DeploymentPlan"]
    assert plan["required"] == ["system", "compute_nodes"]
    assert plan["additionalProperties"] is False
    assert "pattern" in plan["properties"]["components"]["propertyNames"]
    module = schema["$defs"]["ComponentSpec"]["properties"]["module"]["anyOf"]
    assert any("pattern" in m for m in module)  # a spec, or null: to generate
    limit = schema["$defs"]["FabricSpec"]["properties"]["max_sample_bytes"]
    assert (limit["minimum"], limit["maximum"], limit["default"]) == (65536, 1 << 30, 257 << 20)


names = st.text("abcdefghijklmnopqrstuvwxyz0123456789_-.", min_size=1, max_size=8)
endpoints = st.builds("tcp/127.0.0.1:{}".format, st.integers(1, 65535))
scalars = st.one_of(st.booleans(), st.integers(-(2**31), 2**31), st.text(max_size=10))


@st.composite
def plans(draw: st.DrawFn) -> DeploymentPlan:
    nodes = draw(st.lists(names, min_size=1, max_size=3, unique=True))
    comps = draw(st.lists(names, max_size=4, unique=True))
    return DeploymentPlan(
        system=draw(names),
        compute_nodes={
            n: ComputeNode(
                listen=draw(st.lists(endpoints, max_size=2)),
                connect=draw(st.lists(endpoints, max_size=2)),
            )
            for n in nodes
        },
        knowledge=KnowledgeSpec(
            backend="sqlite", node=draw(st.sampled_from(nodes)), path=draw(st.text(max_size=8))
        ),
        components={
            c: ComponentSpec(
                module=f"pkg.nodes:n{i}",
                stage=draw(st.sampled_from(Stage)),
                node=draw(st.sampled_from(nodes)),
                config=draw(st.dictionaries(st.sampled_from(["a", "b", "c"]), scalars)),
            )
            for i, c in enumerate(comps)
        },
    )


@given(plans())
def test_every_valid_plan_round_trips_through_yaml(plan: DeploymentPlan) -> None:
    text = msgspec.yaml.encode(plan).decode()
    assert parse_plan(text).plan == plan
