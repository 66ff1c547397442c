"""Loading a compute node's share: each failure names the plan's line and the fix."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from maplek_runner import LoadError, load_share
from rap_schemas import Stage, parse_plan

from services.maplek_runner.tests import sample_nodes  # the name plans use (see plans.py)
from services.maplek_runner.tests.plans import BROKEN, PLAN, SAMPLE


@pytest.fixture(autouse=True)
def fresh_config() -> Iterator[None]:
    """Loading configures the module-level Nodes: undo it after each test."""
    yield
    sample_nodes.relay.config = sample_nodes.RelayConfig()


def test_the_share_of_a_compute_node_is_imported_checked_and_configured() -> None:
    share = load_share(parse_plan(PLAN, "p.yaml"), "laptop")
    assert share.nodes == [sample_nodes.echo, sample_nodes.relay]
    assert share.system == "demo"
    assert [c.where for c in share.components] == ["p.yaml:6:3", "p.yaml:10:3"]
    assert sample_nodes.relay.config == sample_nodes.RelayConfig(reply="tack")
    assert [c.spec.stage for c in load_share(parse_plan(PLAN), "robot").components] == [Stage.PLAN]


def test_only_the_modules_of_this_compute_node_are_imported() -> None:
    plan = PLAN.replace(f"{SAMPLE}:silent", f"{BROKEN}:silent")
    assert load_share(parse_plan(plan), "laptop").nodes == [sample_nodes.echo, sample_nodes.relay]


def test_an_unknown_compute_node_lists_the_plans_nodes() -> None:
    with pytest.raises(LoadError, match=r"^p.yaml: compute node 'desk' .* are: laptop, robot$"):
        load_share(parse_plan(PLAN, "p.yaml"), "desk")


def test_a_compute_node_with_nothing_to_run_has_an_empty_share() -> None:
    plan = PLAN.replace("  robot: {}", "  robot: {}\n  spare: {}")
    share = load_share(parse_plan(plan, "p.yaml"), "spare")
    assert (share.compute_node, share.components, share.nodes) == ("spare", (), [])


@pytest.mark.parametrize(
    ("old", "new", "where", "words"),
    [
        (
            f"{SAMPLE}:echo",
            "services.maplek_runner.tests.sample_nodez:echo",
            "p.yaml:7:13",
            [
                "component 'echo'",
                "cannot import module 'services.maplek_runner.tests.sample_nodez'",
                "No module named",
                "check the spelling",
            ],
        ),
        (
            f"{SAMPLE}:echo",
            f"{BROKEN}:echo",
            "p.yaml:7:13",
            ["RuntimeError: this module is broken on purpose", "fix the error in that module"],
        ),
        (
            f"{SAMPLE}:echo",
            f"{SAMPLE}:eco",
            "p.yaml:7:13",
            ["has no attribute 'eco'", "its Nodes are: echo, echo_again, relay, silent"],
        ),
        (
            f"{SAMPLE}:echo",
            f"{SAMPLE}:not_a_node",
            "p.yaml:7:13",
            [f"{SAMPLE}:not_a_node is a str, not a rap_sdk.Node", "point module: at a Node"],
        ),
        (
            "    stage: monitor",
            "    stage: execute",
            "p.yaml:8:12",
            ["'execute' in the plan", "Node 'echo' declares 'monitor'", "agree"],
        ),
        (
            f"  relay:\n    module: {SAMPLE}:relay",
            f"  relay:\n    module: {SAMPLE}:echo_again",
            "p.yaml:11:13",
            ["component 'relay' loads the same Node object as component 'echo' (p.yaml:6:3)"],
        ),
        (
            "  echo:\n",
            "  echo1:\n",
            "p.yaml:6:3",
            ["component 'echo1' loads Node 'echo'", "rename the component to 'echo'"],
        ),
        (
            "{reply: tack}",
            "{reply: 7}",
            "p.yaml:14:21",
            ["component 'relay'", "Expected `str`, got `int` - at `$.reply`", "fix config:"],
        ),
        (
            "{reply: tack}",
            "{replay: tack}",
            "p.yaml:14:13",
            ["unknown field `replay`"],
        ),
        (
            "    stage: monitor",
            "    stage: monitor\n    config: {a: 1}",
            "p.yaml:9:13",
            ["Node 'echo' declares no config Struct", "remove config:"],
        ),
    ],
)
def test_each_loading_mistake_names_the_component_line_and_the_fix(
    old: str, new: str, where: str, words: list[str]
) -> None:
    assert old in PLAN
    with pytest.raises(LoadError) as exc:
        load_share(parse_plan(PLAN.replace(old, new, 1), "p.yaml"), "laptop")
    message = str(exc.value)
    assert message.startswith(where + ": "), message
    for word in words:
        assert word in message, message
    assert sample_nodes.relay.config == sample_nodes.RelayConfig()  # nothing applied
