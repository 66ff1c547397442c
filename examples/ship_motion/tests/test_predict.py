"""The three predictors give paths of the right shape; physics beats kinematics in a turn;
the score measures how wrong a predictor has lately been."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ship_motion.learn import train_onnx
from ship_motion.physics import History, ScenarioSpec, ShipCommand, ShipState, simulate
from ship_motion.predict import (
    DataDrivenPredictor,
    DynamicPredictor,
    KinematicPredictor,
    ModelError,
    PredictedPath,
    ScoreTracker,
    model_hash,
    path_error,
    replay_error,
)

CRUISE = math.sqrt(46.0) - 1.0
"""The default ship's steady speed at 3 rps, m/s (thrust equals resistance)."""
START = ShipState(t=0.0, x=0.0, y=0.0, psi=0.0, u=CRUISE, v=0.0, r=0.0, rps=3.0)


def rudder_step(at: float, degrees: float = 20.0, seconds: float = 200.0) -> History:
    """Straight ahead, then the rudder put over at ``at`` and held: a turn in calm water."""
    command = {
        False: ShipCommand(rudder=0.0, rps=3.0),
        True: ShipCommand(rudder=math.radians(degrees), rps=3.0),
    }
    return simulate(
        ScenarioSpec(duration_s=seconds, start=START),
        controller=lambda state, _dt: command[state.t >= at],
    )


def test_every_predictor_gives_thirty_seconds_at_one_second_steps(
    runs: dict[int, History],
) -> None:
    history = runs[0].between(0.0, 600.0)
    model = train_onnx(history)
    recent = history[-10:]
    for predictor in (KinematicPredictor(), DynamicPredictor(), DataDrivenPredictor(model)):
        path = predictor.predict(recent)
        assert path.predictor == predictor.name
        assert path.t0 == recent.t[-1]
        assert len(path.x) == len(path.y) == len(path.psi) == 30
        assert path.times == pytest.approx([path.t0 + k for k in range(1, 31)])
        assert all(-math.pi <= a <= math.pi for a in path.psi)
        # the ship makes headway: after 30 s it is a good 100 m on
        start = recent.data[-1, 1:3]
        assert math.hypot(path.x[-1] - start[0], path.y[-1] - start[1]) > 100.0
    data_driven = DataDrivenPredictor(model)
    assert data_driven.model_hash == model_hash(model)
    assert data_driven.predict(recent.states()).model_hash == model_hash(model)
    with pytest.raises(ValueError, match="last 4 samples"):
        data_driven.predict(recent[-2:])


def test_in_a_turn_the_dynamic_predictor_beats_the_kinematic_one() -> None:
    h = rudder_step(at=60.0)
    kinematic, dynamic = KinematicPredictor(), DynamicPredictor()
    for t0 in (62.0, 63.0, 65.0, 70.0):
        recent = h.between(0.0, t0 + 0.5)
        k_err = path_error(kinematic.predict(recent), h)
        d_err = path_error(dynamic.predict(recent), h)
        assert k_err is not None
        assert d_err is not None
        # the rudder is going over (it turns at 5 degrees/s) or is over: the kinematic model
        # only sees the turn so far, the dynamic one knows where the rudder takes the ship
        assert d_err < 0.5 * k_err, (t0, d_err, k_err)
        assert k_err > 4.0
        if t0 >= 65.0:  # the rudder has arrived: held, it is what the ship will do
            assert d_err < 0.1, (t0, d_err)
    # on a straight course in calm water both are close to exact
    straight = h.between(0.0, 60.0)
    assert replay_error(kinematic, straight, every=5) < 0.5
    assert replay_error(dynamic, straight, every=5) < 0.5


def test_the_score_tracks_matured_predictions_over_a_sliding_window() -> None:
    h = rudder_step(at=100.0, seconds=300.0)
    predictor = KinematicPredictor()
    full, short = ScoreTracker(window=10), ScoreTracker(window=10, horizon_s=10.0)
    scores: list[float | None] = []
    short_scores: list[float | None] = []
    for sample in h:
        scores.append(full.observe(sample))
        short_scores.append(short.observe(sample))
        path = predictor.predict([sample])
        full.add(path)
        short.add(path)
    # nothing has matured in the first 30 s (10 s for the shorter horizon)
    assert scores[:30] == [None] * 30
    assert short_scores[:10] == [None] * 10
    assert short_scores[10] is not None
    assert full.matured == len(h) - 30
    # straight ahead the kinematic prediction is exact
    assert scores[90] == pytest.approx(0.0, abs=1e-6)
    # the turn's onset spoils it; once the turn is steady, constant turn rate is right again
    in_turn = [score for score in scores[110:200] if score is not None]
    peak = max(in_turn)
    assert peak > 5.0
    last = scores[-1]
    assert last is not None
    assert last < 0.2 * peak
    # scored over 10 s instead of 30 s the same predictions err less
    peak_at = 110 + in_turn.index(peak)
    short_then = short_scores[peak_at]
    assert short_then is not None
    assert short_then < peak
    with pytest.raises(ValueError, match="increasing time"):
        full.observe(h.states()[0])


def test_paths_and_models_are_validated() -> None:
    with pytest.raises(ValueError, match="non-finite"):
        PredictedPath(predictor="k", t0=0.0, step=1.0, x=[math.nan], y=[0.0], psi=[0.0])
    with pytest.raises(ValueError, match="one length"):
        PredictedPath(predictor="k", t0=0.0, step=1.0, x=[0.0, 1.0], y=[0.0], psi=[0.0])
    with pytest.raises(ModelError, match="not a valid ONNX model"):
        DataDrivenPredictor(b"not a model at all")
    with pytest.raises(ModelError, match="non-empty"):
        DataDrivenPredictor(b"")
    assert np.isfinite(np.array(KinematicPredictor().predict([START]).x)).all()
