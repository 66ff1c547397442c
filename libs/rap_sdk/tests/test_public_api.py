"""The public surface is what ``__all__`` says, and every name in it exists."""

from __future__ import annotations

import importlib

import pytest
import rap_schemas
import rap_sdk
from rap_sdk import errors

SDK = {
    "BackpressureTimeout",
    "Clock",
    "ConfigError",
    "Context",
    "ContextKnowledge",
    "Fabric",
    "FabricError",
    "HandlerError",
    "InboxPolicy",
    "KnowledgeClient",
    "KnowledgeError",
    "KnowledgeTypeError",
    "LifecycleError",
    "LivelinessChange",
    "MemoryBus",
    "MemoryFabric",
    "Node",
    "NodeGroup",
    "NodeRuntime",
    "NodeStats",
    "Opener",
    "OutgoingEnvelope",
    "Overflow",
    "QueryError",
    "QueryRequest",
    "RapError",
    "RejectedSample",
    "Reply",
    "Sample",
    "Sealer",
    "SenderStats",
    "SystemClock",
    "ZenohConfig",
    "ZenohFabric",
    "await_alive",
    "run",
    "run_nodes",
    "serve",
}
SCHEMAS = {
    "MESSAGES",
    "MODELS_PREFIX",
    "NEW_PLAN",
    "PLAN_REJECTED",
    "VERDICT",
    "limits",
    "KbDelete",
    "KbGet",
    "KbHistory",
    "KbList",
    "KbPut",
    "KbRecord",
    "KbReply",
    "KbRequest",
    "ModelGet",
    "ModelList",
    "ModelMeta",
    "ModelPin",
    "ModelPut",
    "Empty",
    "Envelope",
    "Access",
    "KnowledgeAccess",
    "LaserScan",
    "LidarMask",
    "LogRecord",
    "Message",
    "Odometry",
    "PlanProposal",
    "Pose2D",
    "Rejection",
    "SimTime",
    "SpinCommand",
    "SpinPlan",
    "Stage",
    "StageTrace",
    "TrustCause",
    "TrustOutput",
    "TrustSpecStatus",
    "TrustSpecUpdate",
    "TrustVerdict",
    "Twist",
    "Verdict",
    "by_type",
    "keys",
    "pack_flags",
    "pack_ranges",
    "ComponentSpec",
    "ComputeNode",
    "DeploymentPlan",
    "KnowledgeSpec",
    "PlanDocument",
    "PlanError",
    "load_plan",
    "parse_plan",
}


@pytest.mark.parametrize(("module", "expected"), [(rap_sdk, SDK), (rap_schemas, SCHEMAS)])
def test_all_is_the_public_surface(module: object, expected: set[str]) -> None:
    names = set(module.__all__)  # type: ignore[attr-defined]
    assert names == expected
    for name in names:
        assert getattr(module, name) is not None


@pytest.mark.parametrize(
    "module",
    [
        "rap_sdk.testing",
        "rap_sdk.fabric",
        "rap_schemas.keys",
        "rap_schemas.plan",
        "rap_schemas.yamlconf",
    ],
)
def test_submodules_export_what_they_name(module: str) -> None:
    mod = importlib.import_module(module)
    for name in mod.__all__:
        assert hasattr(mod, name), f"{module}.__all__ names missing {name}"


def test_every_sdk_error_is_a_rap_error_and_documented() -> None:
    for name in errors.__all__:
        cls = getattr(errors, name)
        assert issubclass(cls, errors.RapError)
        assert name in (errors.__doc__ or ""), f"{name} is missing from the error tree"
