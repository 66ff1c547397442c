"""The data-driven model: trained in numpy, served from ONNX, and - the case's point - a model
retrained after the weather changed predicts better than the one trained before it."""

from __future__ import annotations

import time

import numpy as np
import onnx
import pytest

from ship_motion.features import FeatureSpec, features, windows
from ship_motion.learn import (
    TrainingError,
    bad_model,
    evaluate,
    to_onnx,
    train,
    train_onnx,
)
from ship_motion.physics import History
from ship_motion.predict import SPEC_KEY, DataDrivenPredictor, ModelError, ScoreTracker, ServedModel

ONSET = 900.0
"""When the weather front sets in, in the runs of conftest.py; it ramps up over 60 s."""
RAMP_END = ONSET + 60.0
PRE = (60.0, 800.0)
"""Calm data the running model was trained on (after the first minute's transient)."""
CALM_CHECK = (800.0, ONSET + 1.0)
"""Calm data it never saw: windows ending at the onset at the latest."""
POST = (RAMP_END, RAMP_END + 600.0)
"""Ten minutes of data in the new weather: what the loop collects to retrain on."""
TEST = (RAMP_END + 600.0, np.inf)
"""Later data in the same weather, seen by neither model."""


def test_onnx_round_trip_matches_numpy(runs: dict[int, History]) -> None:
    history = runs[0].between(*PRE)
    model = train(history)
    served = ServedModel(to_onnx(model))
    assert served.spec == model.spec
    rows = windows(history, model.spec, future=False)
    x = features(history, rows, model.spec)
    ours, theirs = model.predict(x), served.run(x)
    assert theirs.shape == ours.shape == (len(rows), 90)
    # float32 in the graph against float64 in numpy, on outputs of up to ~200 m
    assert np.abs(theirs - ours).max() < 1e-2
    assert np.allclose(theirs, ours, rtol=1e-4, atol=1e-2)
    # the bytes are deterministic and carry their feature layout
    assert to_onnx(train(history)) == to_onnx(model)
    meta = {p.key: p.value for p in onnx.load_model_from_string(to_onnx(model)).metadata_props}
    assert FeatureSpec.decode(meta[SPEC_KEY]) == model.spec


def test_training_takes_well_under_a_second_and_refuses_too_little_data(
    runs: dict[int, History],
) -> None:
    history = runs[1].between(*POST)
    began = time.perf_counter()
    train_onnx(history)
    assert time.perf_counter() - began < 2.0
    with pytest.raises(TrainingError, match="needs at least 60"):
        train(history[:80])


def test_retraining_after_the_disturbance_lowers_the_prediction_error(
    runs: dict[int, History],
) -> None:
    figures = {}
    for seed in sorted(runs):
        h = runs[seed]
        old = train_onnx(h.between(*PRE))
        new = train_onnx(h.between(*POST))
        bad = bad_model(h.between(*POST))
        test = h.between(*TEST)
        calm = evaluate(old, h.between(*CALM_CHECK))
        stale, fresh, wrong = evaluate(old, test), evaluate(new, test), evaluate(bad, test)
        # per seed, mean position errors in metres: the old model in calm water, the old
        # model in the new weather, the retrained model there, the bad model there
        figures[seed] = (calm, stale, fresh, wrong)
        # the old model was good in the weather it knew, and the weather spoiled it
        assert stale > 2.0 * calm, figures
        # the key property: retrained on post-onset data, the error drops by a clear margin
        assert fresh < 0.6 * stale, figures
        # the planted bad model is far worse than either
        assert wrong > 3.0 * stale, figures
        assert wrong > 10.0 * fresh, figures


def test_the_running_models_score_rises_after_the_onset(runs: dict[int, History]) -> None:
    """What the loop's Analyse will watch: the data-driven predictor's score, online."""
    h = runs[0]
    predictor = DataDrivenPredictor(train_onnx(h.between(*PRE)))
    tracker = ScoreTracker(window=10)
    score_at: dict[float, float | None] = {}
    for row in range(len(h)):
        sample = h[row : row + 1]
        t = float(sample.t[0])
        score_at[t] = tracker.observe(next(iter(sample)))
        if row + 1 >= predictor.needs:
            tracker.add(predictor.predict(h[row + 1 - predictor.needs : row + 1]))
    before = [s for t, s in score_at.items() if 100.0 <= t <= ONSET and s is not None]
    after = [s for t, s in score_at.items() if t >= RAMP_END + 60.0 and s is not None]
    assert max(before) < 5.0
    assert min(after) > 2.0 * max(before)
    assert np.mean(after) > 3.0 * np.mean(before)


def test_windows_never_span_a_gap_in_the_history(runs: dict[int, History]) -> None:
    history = runs[0].between(*PRE)
    spec = FeatureSpec()
    whole = windows(history, spec, future=True)
    assert len(whole) == len(history) - spec.lags - spec.horizon + 1
    # one sample lost: every window that would have covered it is gone, the rest remain
    gappy = History(np.delete(history.data, 300, axis=0))
    kept = windows(gappy, spec, future=True)
    assert len(kept) == len(whole) - (spec.lags + spec.horizon)
    assert np.isfinite(evaluate(train_onnx(history), gappy))


def test_evaluate_refuses_what_cannot_be_served(runs: dict[int, History]) -> None:
    history = runs[0].between(*PRE)
    with pytest.raises(ModelError, match="not a valid ONNX model"):
        evaluate(b"\x08\x07garbage", history)
    proto = onnx.load_model_from_string(train_onnx(history))
    del proto.metadata_props[:]
    with pytest.raises(ModelError, match="feature layout"):
        evaluate(proto.SerializeToString(), history)
    with pytest.raises(ValueError, match="no complete window"):
        evaluate(train_onnx(history), history[:20])
