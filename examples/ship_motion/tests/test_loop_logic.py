"""What the ship's predictors and the stages decide, apart from the fabric (ship_motion.loop)."""

from __future__ import annotations

import os

import pytest
from rap_sdk.twin import TwinKind, ask

from ship_motion.learn import bad_model, train_onnx
from ship_motion.loop import (
    Detector,
    HashMismatch,
    ReplayBelief,
    ReplayTwin,
    ShipPredictors,
    judge,
    training_due,
    training_window,
)
from ship_motion.physics import History
from ship_motion.predict import ModelError, model_hash

ONSET = 900.0
CALM = (0.0, 800.0)
FRONT = (1000.0, 1600.0)


def test_the_display_falls_back_while_no_model_or_a_drifting_one_is_served(
    runs: dict[int, History],
) -> None:
    history = runs[0]
    ship = ShipPredictors()
    steps = [ship.observe(s) for s in history.between(0.0, 50.0)]
    assert all(s.fallback for s in steps), "no model served: physics paths on the display"
    assert all(s.display.predictor in ("kinematic", "dynamic") for s in steps)
    model = train_onnx(history.between(*CALM))
    ship.load(1, model, model_hash(model))
    drifted = [ship.observe(s) for s in history.between(50.0, 1500.0)]
    assert not drifted[0].fallback
    assert drifted[0].display.predictor == "data_driven"
    calm = [s for s in drifted if s.display.t0 < ONSET]
    assert sum(s.fallback for s in calm) == 0, "the calm model is trusted in calm weather"
    late = [s for s in drifted if s.display.t0 > 1100.0]
    assert late
    assert all(s.fallback for s in late), "in the front its score says fall back"
    assert all(s.scores["data_driven"] > ship.safe_threshold for s in late)
    # every sample had a path for the display
    assert all(
        s.display.t0 == t
        for s, t in zip(drifted, [p.t for p in history.between(50.0, 1500.0)], strict=True)
    )


def test_a_model_whose_bytes_are_not_the_pinned_ones_is_not_served(
    runs: dict[int, History],
) -> None:
    model = train_onnx(runs[0].between(*CALM))
    ship = ShipPredictors()
    with pytest.raises(HashMismatch, match="not loaded"):
        ship.load(2, model, "0" * 64)
    corrupt = os.urandom(512)
    with pytest.raises(ModelError):
        ship.load(3, corrupt, model_hash(corrupt))
    assert ship.learned is None
    assert ship.version == 0


def test_the_detector_needs_consecutive_scored_steps_of_one_model() -> None:
    d = Detector(threshold=5.0, steps=3, min_matured=2)
    assert not d.step(9.0, 1, 1)  # not matured enough
    assert [d.step(9.0, 5, 1) for _ in range(3)] == [False, False, True]
    assert not d.step(1.0, 5, 1)  # a good step resets the run
    assert [d.step(9.0, 5, 1) for _ in range(2)] == [False, False]
    assert not d.step(9.0, 5, 2)  # a new model starts a new run
    assert not d.step(9.0, 5, 0)  # no model served: nothing to judge


def test_plan_waits_for_its_window_and_retries_with_more() -> None:
    assert (training_due(650.0, 0, 1369.0, 720.0), training_due(650.0, 0, 1370.0, 720.0)) == (
        False,
        True,
    )
    assert training_window(650.0, 1370.0, 120.0) == (650.0, 1250.0)
    # after a rejected candidate: another collect_s of data
    assert (training_due(650.0, 1, 1370.0, 720.0), training_due(650.0, 1, 2090.0, 720.0)) == (
        False,
        True,
    )


def test_legitimate_rejects_every_planted_candidate_and_approves_a_good_one(
    runs: dict[int, History],
) -> None:
    for seed, history in runs.items():
        running = train_onnx(history.between(*CALM))
        front = history.between(*FRONT)
        good = train_onnx(history.between(FRONT[0], FRONT[1] - 120.0))
        verdict = judge(good, running, front, threshold=5.0, margin=0.1)
        assert verdict.approved, (seed, verdict)
        assert verdict.candidate_error < verdict.running_error
        for planted in (bad_model(front), running, os.urandom(2048), b""):
            verdict = judge(planted, running, front, threshold=5.0, margin=0.1)
            assert not verdict.approved, (seed, verdict)
            assert verdict.reason
        # above the threshold even with no running model to compare with
        assert not judge(bad_model(front), None, front, threshold=5.0).approved


@pytest.mark.anyio
async def test_legitimate_is_a_replay_twin(runs: dict[int, History]) -> None:
    history = runs[1]
    running = train_onnx(history.between(*CALM))
    front = history.between(*FRONT)
    twin = ReplayTwin(threshold=5.0, margin=0.1)
    good = train_onnx(history.between(FRONT[0], FRONT[1] - 120.0))
    report = await ask(twin, good, ReplayBelief(history=front, running=running))
    assert report.kind is TwinKind.REPLAY
    assert report.verdict is None
    assert report.metrics["candidate_error_m"] < report.metrics["running_error_m"]
    assert report.horizon_s == pytest.approx(FRONT[1] - FRONT[0] - 1.0)
    assert report.elapsed_s > 0
    assert not report.belief.thin
    bad = await ask(twin, bad_model(front), ReplayBelief(history=front, running=running))
    assert bad.verdict is not None
    assert bad.verdict.startswith("error-above-threshold: replay error")
    short = await ask(twin, good, ReplayBelief(history=front.between(1000.0, 1100.0), running=None))
    assert short.belief.thin
    assert "no running model to compare with" in short.belief.notes


def test_a_restarted_clock_starts_the_predictors_history_afresh(runs: dict[int, History]) -> None:
    history = runs[0]
    model = train_onnx(history.between(*CALM))
    ship = ShipPredictors()
    ship.load(1, model, model_hash(model))
    for s in history.between(0.0, 100.0):
        ship.observe(s)
    again = [ship.observe(s) for s in history.between(0.0, 50.0)]
    assert ship.restarted == 1
    assert ship.version == 1
    assert any(p.predictor == "data_driven" for p in again[-1].paths)
    # a gap in the samples skips the data-driven path, it does not unload the model
    gap = ship.observe(next(iter(history.between(60.0, 61.0))))
    assert [p.predictor for p in gap.paths] == ["kinematic", "dynamic"]
    assert ship.learned is not None
