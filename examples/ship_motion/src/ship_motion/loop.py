"""What the ship's predictors and the MAPLE-K stages decide, apart from the fabric.

The generated nodes (``ship_motion.nodes``) call these between their region markers:
they stay small, and this module is tested on its own.

- :class:`ShipPredictors`: the managed system's predictors (kinematic, dynamic, and the
  data-driven model in use), their scores, and the display's safe state.
- :class:`Detector`: Analyse's rule (score above the threshold for N consecutive steps).
- :func:`training_due`, :func:`training_window`: Plan's wait for enough post-anomaly
  history, and what it trains on.
- :func:`judge`: Legitimate's replay of recorded history through candidate and running model.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import msgspec
from rap_sdk.twin import BeliefQuality, Finding, TwinKind, TwinReport

from .learn import TrainingError, errors, train_onnx
from .physics import History, ShipState
from .predict import (
    DataDrivenPredictor,
    DynamicPredictor,
    KinematicPredictor,
    ModelError,
    PredictedPath,
    ScoreTracker,
    model_hash,
)

__all__ = [
    "MODEL_NAME",
    "Detector",
    "HashMismatch",
    "Judgement",
    "ReplayBelief",
    "ReplayTwin",
    "ShipPredictors",
    "Step",
    "history_of",
    "judge",
    "train_candidate",
    "training_due",
    "training_window",
]

MODEL_NAME = "ship_motion"
"""The model store's name for the data-driven model."""


class HashMismatch(ModelError):
    """The bytes the model store gave are not the version Execute pinned."""


@dataclass(frozen=True)
class Step:
    """What the predictors made of one sample."""

    paths: list[PredictedPath]
    """Every predictor that could predict: kinematic, dynamic, data-driven (if served)."""
    display: PredictedPath
    """What the display shows: the data-driven path, or a physics one in the safe state."""
    fallback: bool
    scores: dict[str, float]
    """Mean position error of each predictor's last matured paths, m (0 before any)."""
    matured: int
    """Matured paths of the data-driven model in use."""


@dataclass
class ShipPredictors:
    """The ship's predictors, fed one sample at a time.

    The display shows the data-driven path while a model is served and its score is at most
    ``safe_threshold`` (or not yet known: a model Legitimate approved is trusted until its
    paths mature); otherwise it falls back to the physics predictor with the lower score -
    the safe state, which also covers retraining (the running model's score is what raised
    the anomaly) and any time no model can be served.
    """

    horizon: int = 30
    window: int = 20
    safe_threshold: float = 5.0
    kinematic: KinematicPredictor = field(init=False)
    dynamic: DynamicPredictor = field(init=False)
    learned: DataDrivenPredictor | None = None
    version: int = 0
    trackers: dict[str, ScoreTracker] = field(init=False)
    recent: deque[ShipState] = field(init=False)
    restarted: int = 0
    """Times the samples' time went back (the ship's clock restarted): history dropped."""

    def __post_init__(self) -> None:
        self.kinematic = KinematicPredictor(self.horizon)
        self.dynamic = DynamicPredictor(horizon=self.horizon)
        self.trackers = {name: ScoreTracker(self.window) for name in ("kinematic", "dynamic")}
        self.recent = deque(maxlen=64)

    def load(self, version: int, model_bytes: bytes, expected_hash: str) -> None:
        """Serve ``model_bytes`` as ``version`` if their SHA-256 is ``expected_hash``;
        raises :class:`HashMismatch` or :class:`ModelError` (the model in use stays)."""
        got = model_hash(model_bytes)
        if got != expected_hash:
            raise HashMismatch(
                f"model version {version} has SHA-256 {got[:12]}..., the pinned one "
                f"{expected_hash[:12]}...: not loaded"
            )
        learned = DataDrivenPredictor(model_bytes)
        if learned.spec.horizon != self.horizon:
            raise ModelError(
                f"model version {version} predicts {learned.spec.horizon} steps, the ship "
                f"{self.horizon}"
            )
        self.learned = learned
        self.version = version
        self.trackers["data_driven"] = ScoreTracker(self.window)

    def unload(self) -> None:
        self.learned = None
        self.version = 0
        self.trackers.pop("data_driven", None)

    def observe(self, state: ShipState) -> Step:
        if self.recent and state.t <= self.recent[-1].t:
            # time went back: the ship's clock restarted (a new run); what was recorded
            # belongs to another time line and would score the paths against it
            self.restarted += 1
            self.recent.clear()
            for name in self.trackers:
                self.trackers[name] = ScoreTracker(self.window)
        self.recent.append(state)
        for tracker in self.trackers.values():
            tracker.observe(state)
        paths = [self.kinematic.predict([state]), self.dynamic.predict([state])]
        learned = self.learned
        if learned is not None and len(self.recent) >= learned.needs:
            try:
                paths.append(learned.predict(list(self.recent)[-learned.needs :]))
            except ModelError:
                self.unload()  # a model that gives non-finite paths is not served
            except ValueError:
                pass  # a gap in the samples: no data-driven path until it is filled
        for path in paths:
            self.trackers[path.predictor].add(path)
        scores = {name: t.score or 0.0 for name, t in self.trackers.items()}
        dd = self.trackers.get("data_driven")
        matured = dd.matured if dd is not None else 0
        by_name = {p.predictor: p for p in paths}
        if "data_driven" in by_name and (
            matured == 0 or scores["data_driven"] <= self.safe_threshold
        ):
            return Step(paths, by_name["data_driven"], False, scores, matured)
        physics = min(("kinematic", "dynamic"), key=lambda n: (scores[n] or math.inf, n))
        return Step(paths, by_name[physics], True, scores, matured)


@dataclass
class Detector:
    """An anomaly when the score stays above ``threshold`` for ``steps`` consecutive
    scored steps of one model version (steps without a matured path do not count)."""

    threshold: float = 5.0
    steps: int = 5
    min_matured: int = 5
    run: int = 0
    version: int = -1

    def step(self, score: float, matured: int, version: int) -> bool:
        if version != self.version:
            self.version, self.run = version, 0
        if version == 0 or matured < self.min_matured:
            return False
        self.run = self.run + 1 if score > self.threshold else 0
        return self.run >= self.steps


def training_due(anomaly_t: float, attempts: int, latest_t: float, collect_s: float) -> bool:
    """Plan's wait: after an anomaly at ``anomaly_t``, train once ``collect_s`` seconds of
    history are in (once more for each candidate Legitimate rejected: ``attempts``)."""
    return latest_t >= anomaly_t + collect_s * (1 + attempts)


def training_window(anomaly_t: float, latest_t: float, holdout_s: float) -> tuple[float, float]:
    """From the anomaly to ``holdout_s`` before the latest sample: the rest is kept for
    Legitimate's replay only."""
    return anomaly_t, latest_t - holdout_s


def train_candidate(history: History, start: float, end: float, seed: int = 0) -> bytes:
    """ONNX bytes of a model trained on ``history`` between ``start`` and ``end``."""
    window = history.between(start, end)
    if len(window) < 2:
        raise TrainingError(f"no history between t={start:g} and t={end:g}")
    return train_onnx(window, seed=seed)


class Judgement(msgspec.Struct, frozen=True, kw_only=True):
    approved: bool
    code: str = ""
    """Why not, for counting: ``unservable``, ``no-history``, ``error-above-threshold``,
    ``not-better`` (empty when approved)."""
    reason: str = ""
    candidate_error: float = 0.0
    running_error: float = -1.0
    """-1 when no model was running (or it could not be replayed)."""


def judge(
    candidate: bytes,
    running: bytes | None,
    history: History,
    *,
    threshold: float,
    margin: float = 0.0,
) -> Judgement:
    """Replay ``history`` through the candidate and the running model; approve the
    candidate only if it serves, its mean position error is at most ``threshold`` and not
    above the running model's (minus ``margin``)."""
    try:
        cand = float(errors(candidate, history).mean())
    except ModelError as exc:
        return Judgement(
            approved=False, code="unservable", reason=f"candidate cannot be served: {exc}"
        )
    except ValueError as exc:
        return Judgement(approved=False, code="no-history", reason=f"no history to replay: {exc}")
    if not math.isfinite(cand):
        return Judgement(approved=False, code="unservable", reason="candidate error is not finite")
    run = -1.0
    if running is not None:
        try:
            run = float(errors(running, history).mean())
        except (ModelError, ValueError):
            run = -1.0  # a running model that cannot be replayed does not protect itself
    code = reason = ""
    if cand > threshold:
        code = "error-above-threshold"
        reason = f"replay error {cand:.2f} m is above the threshold {threshold:.2f} m"
    elif run >= 0 and cand > run - margin:
        code = "not-better"
        reason = f"replay error {cand:.2f} m is not below the running model's {run:.2f} m"
    return Judgement(
        approved=not code, code=code, reason=reason, candidate_error=cand, running_error=run
    )


@dataclass(frozen=True)
class ReplayBelief:
    """What Legitimate replays: the recorded history and the model that runs now."""

    history: History
    running: bytes | None


class ReplayTwin:
    """The ship's twin: a REPLAY twin (``rap_sdk.twin``). It does not run the ship forward;
    it replays recorded history through the candidate and the running model, which is
    what "what would happen with this model" means for a predictor."""

    kind = TwinKind.REPLAY

    def __init__(self, *, threshold: float, margin: float = 0.0) -> None:
        self.threshold, self.margin = threshold, margin

    def rollout(self, plan: bytes, belief: ReplayBelief) -> TwinReport:
        j = judge(
            plan, belief.running, belief.history, threshold=self.threshold, margin=self.margin
        )
        span = float(belief.history.t[-1] - belief.history.t[0]) if len(belief.history) else 0.0
        metrics = {"candidate_error_m": j.candidate_error}
        if j.running_error >= 0:
            metrics["running_error_m"] = j.running_error
        findings = [] if j.approved else [Finding(code=j.code, message=j.reason)]
        notes = [] if belief.running is not None else ["no running model to compare with"]
        thin = len(belief.history) < MIN_REPLAY
        if thin:
            notes.append(f"{len(belief.history)} samples replayed, fewer than {MIN_REPLAY}")
        return TwinReport(
            kind=self.kind,
            horizon_s=span,
            findings=findings,
            metrics=metrics,
            belief=BeliefQuality(thin=thin, notes=notes),
        )


MIN_REPLAY = 300
"""Samples of history below which a replay's verdict is marked as resting on thin belief."""


def history_of(states: Sequence[ShipState]) -> History:
    """States (in any order, duplicates allowed) as a History in increasing time."""
    by_t = {s.t: s for s in states}
    return History.from_states([by_t[t] for t in sorted(by_t)])
