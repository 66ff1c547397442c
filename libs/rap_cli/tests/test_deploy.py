"""What a compute node runs (rap_cli.deploy): the processes, in order, and addresses."""

from __future__ import annotations

from pathlib import Path

import msgspec
from rap_cli.deploy import PYTHON, Paths, node_processes, resolve_endpoint, resolve_url
from rap_schemas import PlanDocument, Stage
from rap_schemas.plan import ComponentSpec, ComputeNode, DeploymentPlan, KnowledgeSpec, TrustSpec

PLAN = DeploymentPlan(
    system="ship",
    compute_nodes={
        "companion": ComputeNode(address="192.168.0.115", listen=["tcp/companion:7447"]),
        "deck": ComputeNode(connect=["tcp/companion:7447"]),
    },
    knowledge=KnowledgeSpec(backend="redis", node="companion", url="redis://192.168.0.115:6379/2"),
    trust=TrustSpec(node="companion", specs=["specs/order.dsrv"]),
    components={
        "m": ComponentSpec(module="ship.nodes.m:node", stage=Stage.MONITOR, node="companion"),
        "sim": ComponentSpec(
            external=True, node="deck", run=["{python}", "-m", "sim", "--system", "{system}"]
        ),
    },
)


def test_a_node_name_as_host_goes_to_the_given_address_else_the_models() -> None:
    assert resolve_endpoint("tcp/companion:7447", PLAN) == "tcp/192.168.0.115:7447"
    given = {"companion": "10.0.0.2"}
    assert resolve_endpoint("tcp/companion:7447", PLAN, given) == "tcp/10.0.0.2:7447"
    assert resolve_endpoint("tcp/companion:7447", PLAN, {"companion": "fd00::2"}) == (
        "tcp/[fd00::2]:7447"
    )
    assert resolve_endpoint("tcp/elsewhere:1", PLAN, given) == "tcp/elsewhere:1"
    assert resolve_url("redis://192.168.0.115:6379/2", PLAN, given) == "redis://10.0.0.2:6379/2"
    assert resolve_url("redis://u:p@companion:6379/0", PLAN, given) == (
        "redis://u:p@10.0.0.2:6379/0"
    )
    assert resolve_url("redis://db.example:6379/0", PLAN, given) == "redis://db.example:6379/0"


def test_each_node_runs_its_router_first_then_its_share(tmp_path: Path) -> None:
    doc = PlanDocument.from_plan(PLAN)
    model = tmp_path / "model.yaml"
    companion = node_processes(
        doc,
        "companion",
        paths=Paths.local(model, tmp_path / "run", "companion"),
        addresses={"companion": "127.0.0.1"},
    )
    assert [p.name for p in companion] == ["router", "knowledge", "runner", "trust-order"]
    kb = companion[1]
    assert "redis://127.0.0.1:6379/2" in kb.argv
    assert kb.env["RAP_ZENOH_CONFIG"].endswith("companion/zenoh-client.json5")
    assert companion[3].command("py")[:4] == [
        "py",
        "-m",
        "trust_checker",
        str(tmp_path / "specs/order.dsrv"),
    ]
    deck = node_processes(doc, "deck", paths=Paths.local(model, tmp_path / "run", "deck"))
    assert [p.name for p in deck] == ["router", "sim"]
    assert deck[1].argv == (PYTHON, "-m", "sim", "--system", "ship")


def test_memcached_knowledge_gets_its_url_and_its_sqlite_file(tmp_path: Path) -> None:
    kb_spec = KnowledgeSpec(backend="memcached", node="companion", url="memcached://companion")
    doc = PlanDocument.from_plan(msgspec.structs.replace(PLAN, knowledge=kb_spec))
    paths = Paths.local(tmp_path / "model.yaml", tmp_path / "run", "companion")
    processes = node_processes(doc, "companion", paths=paths, addresses={"companion": "10.0.0.2"})
    argv = next(p for p in processes if p.name == "knowledge").argv
    assert argv[argv.index("--backend") + 1] == "memcached"
    assert argv[argv.index("--memcached-url") + 1] == "memcached://10.0.0.2"
    assert argv[argv.index("--sqlite-path") + 1].endswith("knowledge.sqlite3")


def test_kafka_knowledge_gets_its_broker_and_its_sqlite_file(tmp_path: Path) -> None:
    kb_spec = KnowledgeSpec(backend="kafka", node="companion", url="kafka://companion:9092")
    doc = PlanDocument.from_plan(msgspec.structs.replace(PLAN, knowledge=kb_spec))
    paths = Paths.local(tmp_path / "model.yaml", tmp_path / "run", "companion")
    processes = node_processes(doc, "companion", paths=paths, addresses={"companion": "10.0.0.2"})
    argv = next(p for p in processes if p.name == "knowledge").argv
    assert argv[argv.index("--backend") + 1] == "kafka"
    assert argv[argv.index("--kafka-url") + 1] == "kafka://10.0.0.2:9092"
    assert argv[argv.index("--sqlite-path") + 1].endswith("knowledge.sqlite3")
