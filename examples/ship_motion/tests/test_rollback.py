"""The ship's predictor follows the model store: the version Execute pins (hash checked), and
an admin's rollback to the previous version."""

from __future__ import annotations

import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_sdk.knowledge import KnowledgeClient
from rap_sdk.testing import Harness

from ship_motion import messages
from ship_motion.learn import train_onnx
from ship_motion.loop import MODEL_NAME
from ship_motion.nodes import predictors
from ship_motion.physics import History
from ship_motion.predict import model_hash
from ship_motion.service import pose_message

pytestmark = pytest.mark.anyio
SYSTEM = "ship-rollback"


async def _served(h: Harness, pose: messages.Pose) -> messages.PredictedPath:
    """Publish one pose; the data-driven path it gives (the model's version in it)."""
    mark = len(h.records)
    await h.publish("ship/pose", pose)
    while True:
        rec = await h.expect_event("ship/predicted_path", after=mark)
        mark = h.records.index(rec) + 1
        path = rec.decode(messages.PredictedPath)
        if path.predictor == messages.PredictorKind.DATA_DRIVEN:
            return path


async def test_the_predictor_serves_the_pinned_version_and_follows_a_rollback(
    runs: dict[int, History],
) -> None:
    history = runs[0]
    first = train_onnx(history.between(0.0, 400.0))
    second = train_onnx(history.between(0.0, 800.0), seed=1)
    poses = [pose_message(s) for s in history.between(0.0, 200.0)]
    async with Harness(system=SYSTEM) as h:
        await h.hold(open_service(KnowledgeConfig(system=SYSTEM), fabric=h.fabric))
        kb = await h.hold(KnowledgeClient(fabric=h.fabric, system=SYSTEM, writer="admin"))
        v1 = await kb.put_model(MODEL_NAME, first)
        v2 = await kb.put_model(MODEL_NAME, second)
        await kb.pin_model(MODEL_NAME, v1.version)
        await h.start(predictors.node)
        for pose in poses[:3]:
            await h.publish("ship/pose", pose)
        path = await _served(h, poses[3])
        assert (path.model_version, path.model_hash) == (1, model_hash(first))
        # Execute pins v2 and says so; a message whose hash is not v2's bytes is refused
        await h.publish(
            "ship/model",
            messages.ActiveModel(
                model_key=MODEL_NAME, version=2, model_hash="0" * 64, rollback=False
            ),
        )
        assert (await _served(h, poses[4])).model_version == 1
        await kb.pin_model(MODEL_NAME, v2.version)
        await h.publish(
            "ship/model",
            messages.ActiveModel(
                model_key=MODEL_NAME, version=2, model_hash=v2.sha256, rollback=False
            ),
        )
        path = await _served(h, poses[5])
        assert (path.model_version, path.model_hash) == (2, model_hash(second))
        # an admin rolls back (rap models rollback): the ship serves v1 again within
        # pin_check_every samples
        assert await kb.rollback_model(MODEL_NAME) == 1
        every = predictors.node.config.pin_check_every
        versions = [(await _served(h, p)).model_version for p in poses[6 : 6 + every + 1]]
        assert versions[-1] == 1, versions
        assert versions.index(1) <= every
        assert not h.rejections()
