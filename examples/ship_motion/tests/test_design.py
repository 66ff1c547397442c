"""The case's AADL design (``design/``) imported with RAP's toolkit: what the model holds,
and that ``rap check`` finds nothing wrong with the design nor with the model written
from it. ``design/`` holds no ``RAP.aadl``: the importer knows RAP's property set."""

from __future__ import annotations

from pathlib import Path

import pytest
from rap_cli.designs import checked_import
from rap_cli.importers import Imported
from rap_cli.importers.aadl import import_aadl
from rap_cli.model_io import check_model_text
from rap_cli.model_yaml import model_to_yaml
from rap_schemas.maplek import Stage
from rap_schemas.plan import DeploymentPlan

DESIGN = Path(__file__).parents[1] / "design"


@pytest.fixture(scope="module")
def imported() -> Imported:
    return import_aadl(sorted(DESIGN.glob("*.aadl")))


@pytest.fixture(scope="module")
def plan(imported: Imported) -> DeploymentPlan:
    assert imported.plan is not None, [str(d) for d in imported.diagnostics]
    return imported.plan


def test_the_design_imports_and_checks_clean(imported: Imported) -> None:
    assert not (DESIGN / "RAP.aadl").exists()  # `with RAP;` finds the built-in set
    assert [str(d) for d in imported.diagnostics if d.severity != "note"] == []
    checked = checked_import(imported, str(DESIGN))  # what `rap check design/` reports
    assert checked.ok
    assert [str(d) for d in checked.diagnostics if d.severity != "note"] == []


def test_the_written_model_checks_clean(plan: DeploymentPlan) -> None:
    # what `rap import aadl design -o model.yaml` writes, then `rap check model.yaml`
    checked = check_model_text(model_to_yaml(plan), "model.yaml")
    assert checked.ok, [str(d) for d in checked.diagnostics]
    assert [d for d in checked.diagnostics if d.severity == "warning"] == []
    assert checked.plan is not None
    assert set(checked.plan.components) == set(plan.components)


def test_components_stages_roles_and_nodes(plan: DeploymentPlan) -> None:
    got = {name: (c.stage, c.role, c.external, c.node) for name, c in plan.components.items()}
    assert got == {
        "simulator": (None, "managed", True, "vessel"),
        "predictors": (None, "managed", False, "vessel"),
        "display": (None, "display", True, "vessel"),
        "monitor": (Stage.MONITOR, None, False, "vessel"),
        "analysis": (Stage.ANALYSE, None, False, "shore"),
        "plan": (Stage.PLAN, None, False, "shore"),
        "legitimate": (Stage.LEGITIMATE, None, False, "shore"),
        "execute": (Stage.EXECUTE, None, False, "vessel"),
    }
    assert all(c.module is None for c in plan.components.values())  # rap generate fills them


def test_ports_kinds_types_and_topics(plan: DeploymentPlan) -> None:
    ports = {
        (name, pname): (p.direction, p.kind, p.type, p.topic)
        for name, c in plan.components.items()
        for pname, p in c.ports.items()
    }
    assert ports == {
        ("simulator", "pose"): ("out", "data", "Pose", "ship/pose"),
        ("simulator", "weather"): ("out", "data", "Weather", "ship/weather"),
        ("predictors", "pose"): ("in", "data", "Pose", "ship/pose"),
        ("predictors", "model"): ("in", "data", "ActiveModel", "ship/model"),
        ("predictors", "predicted_path"): (
            "out",
            "event-data",
            "PredictedPath",
            "ship/predicted_path",
        ),
        ("predictors", "score"): (
            "out",
            "event-data",
            "PredictionScore",
            "ship/prediction_score",
        ),
        ("display", "predicted_path"): (
            "in",
            "event-data",
            "PredictedPath",
            "ship/predicted_path",
        ),
        ("monitor", "pose"): ("in", "data", "Pose", "ship/pose"),
        ("monitor", "weather"): ("in", "data", "Weather", "ship/weather"),
        ("monitor", "score"): ("in", "event-data", "PredictionScore", "ship/prediction_score"),
        ("monitor", "new_data"): ("out", "event", None, "new-data"),
        ("analysis", "new_data"): ("in", "event", None, "new-data"),
        ("analysis", "anomaly"): ("out", "event-data", "Anomaly", "anomaly"),
        ("plan", "new_data"): ("in", "event", None, "new-data"),
        ("plan", "anomaly"): ("in", "event-data", "Anomaly", "anomaly"),
        ("plan", "verdict"): ("in", "event-data", "Verdict", "model-verdict"),
        ("plan", "proposal"): ("out", "event-data", "ModelPlan", "new-plan"),
        ("legitimate", "proposal"): ("in", "event-data", "ModelPlan", "new-plan"),
        ("legitimate", "approved"): ("out", "event-data", "ModelPlan", "verdict"),
        ("legitimate", "verdict"): ("out", "event-data", "Verdict", "model-verdict"),
        ("execute", "approved"): ("in", "event-data", "ModelPlan", "verdict"),
        ("execute", "model"): ("out", "data", "ActiveModel", "ship/model"),
    }


def test_knowledge_keys_and_config(plan: DeploymentPlan) -> None:
    c = plan.components
    assert c["monitor"].writes == ["ship_pose", "weather", "prediction_score"]
    assert (c["analysis"].reads, c["analysis"].writes) == (
        ["prediction_score", "handling_anomaly", "active_model"],
        ["anomaly", "handling_anomaly"],
    )
    assert c["plan"].reads == ["ship_pose", "anomaly"]
    assert c["execute"].writes == ["active_model", "handling_anomaly"]
    assert c["execute"].config == {"plan_max_age": 60.0}
    # the model store: Plan puts candidates, Execute pins, Legitimate and the ship read
    assert {n: dict(x.models) for n, x in c.items() if x.models} == {
        "predictors": {"ship_motion": "read"},
        "plan": {"ship_motion": "write"},
        "legitimate": {"ship_motion": "read"},
        "execute": {"ship_motion": "write"},
    }


def test_messages_and_field_types(plan: DeploymentPlan) -> None:
    messages = plan.messages
    assert set(messages) == {
        "Pose",
        "Weather",
        "PredictedPath",
        "PredictionScore",
        "PredictorKind",
        "Anomaly",
        "ModelPlan",
        "Verdict",
        "ActiveModel",
    }
    assert messages["PredictorKind"].enum == ["kinematic", "dynamic", "data_driven"]

    def fields(name: str) -> dict[str, str]:
        return {f: spec.type for f, spec in messages[name].fields.items()}

    assert list(fields("Pose")) == ["t", "x", "y", "psi", "u", "v", "r", "rudder", "rps"]
    assert set(fields("Pose").values()) == {"float", "float64"}
    path = fields("PredictedPath")
    assert (path["predictor"], path["x"], path["model_version"]) == (
        "PredictorKind",
        "list[float64]",
        "int64",
    )
    assert fields("ModelPlan")["version"] == "int64"
    assert messages["ModelPlan"].fields["version"].ge == 1
    assert messages["PredictedPath"].fields["step"].gt == 0.0
    assert fields("Verdict")["approved"] == "bool"
    assert fields("ActiveModel") == {
        "model_key": "str",
        "version": "int64",
        "model_hash": "str",
        "rollback": "bool",
    }


def test_compute_nodes_bus_knowledge_and_connections(plan: DeploymentPlan) -> None:
    nodes = plan.compute_nodes
    assert {n: (c.address, c.listen, c.connect) for n, c in nodes.items()} == {
        "vessel": ("192.0.2.30", [], ["tcp/shore:7447"]),
        "shore": ("192.0.2.40", ["tcp/shore:7447"], []),
    }
    assert (plan.buses["link"].kind, plan.buses["link"].nodes) == ("radio", ["vessel", "shore"])
    assert plan.knowledge.node == "shore"
    links = {(c.from_, c.to): c.bus for c in plan.connections}
    assert len(links) == len(plan.connections) == 12
    # what crosses the radio link is bound to it; what stays on one computer is not
    assert {ends for ends, bus in links.items() if bus == "link"} == {
        ("monitor.new_data", "analysis.new_data"),
        ("legitimate.approved", "execute.approved"),
        ("monitor.new_data", "plan.new_data"),
    }
    for ends, bus in links.items():
        src, dst = (plan.components[end.split(".")[0]].node for end in ends)
        assert (bus == "link") == (src != dst), ends


def test_threads_and_their_dispatch(plan: DeploymentPlan) -> None:
    got = {
        (name, tname): (t.dispatch.kind, t.dispatch.rate_hz) if t.dispatch else None
        for name, c in plan.components.items()
        for tname, t in c.threads.items()
    }
    assert got == {
        ("simulator", "step"): ("periodic", 10.0),
        ("predictors", "physics"): ("sporadic", 1.0),  # on each pose sample
        ("predictors", "learned"): ("sporadic", 1.0),
        ("monitor", "collect"): ("sporadic", 10.0),
        ("analysis", "detect"): ("sporadic", 1.0),
        ("plan", "planner"): ("sporadic", 1.0),
        ("plan", "trainer"): ("sporadic", None),  # AADL Aperiodic
    }
