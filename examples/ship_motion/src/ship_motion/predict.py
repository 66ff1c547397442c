"""Three predictors of the ship's path, and a score of how wrong each has lately been.

- :class:`KinematicPredictor` keeps the speed over ground, the drift angle and the rate of
  turn of the last sample (constant turn rate and velocity).
- :class:`DynamicPredictor` integrates the equations of motion of
  :mod:`ship_motion.physics` with the rudder and propeller held as they are, in calm water:
  it knows the ship, not the weather.
- :class:`DataDrivenPredictor` runs a learned model (ONNX bytes, served by onnxruntime;
  see :mod:`ship_motion.learn`) on the last few samples.

Each turns the recent samples (oldest first, one per sample period) into a
:class:`PredictedPath`. A :class:`ScoreTracker` holds the paths until what happened is known
and scores the predictor by the mean distance between predicted and actual positions over
its most recent matured paths.
"""

from __future__ import annotations

import hashlib
import math
from collections import deque
from collections.abc import Sequence
from typing import Protocol, cast

import numpy as np
import onnx
import onnxruntime as ort  # type: ignore[import-untyped]
from google.protobuf.message import DecodeError  # type: ignore[import-untyped]

from .features import FeatureSpec, features, to_earth, windows
from .physics import _S, FloatArray, History, ShipParams, ShipState, Vector6, rk4_step, wrap_angle

__all__ = [
    "INPUT",
    "OUTPUT",
    "SPEC_KEY",
    "DataDrivenPredictor",
    "DynamicPredictor",
    "KinematicPredictor",
    "ModelError",
    "PredictedPath",
    "Predictor",
    "ScoreTracker",
    "ServedModel",
    "model_hash",
    "path_error",
    "replay",
    "replay_error",
]

INPUT = "features"
OUTPUT = "displacements"
SPEC_KEY = "ship_motion.feature_spec"
"""The model metadata entry that holds the :class:`FeatureSpec` a model was trained for."""


class PredictedPath(_S, frozen=True, kw_only=True):
    """Where a predictor expects the ship at ``t0 + step``, ``t0 + 2 step``, ..."""

    predictor: str
    t0: float
    step: float
    x: list[float]
    y: list[float]
    psi: list[float]
    model_hash: str | None = None
    """For a learned model, the SHA-256 of its ONNX bytes."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.step > 0:
            raise ValueError(f"PredictedPath.step is {self.step}: it must be above 0")
        if not self.x or not len(self.x) == len(self.y) == len(self.psi):
            raise ValueError("PredictedPath needs x, y and psi of one length, at least 1")
        for name in ("x", "y", "psi"):
            if not all(math.isfinite(value) for value in getattr(self, name)):
                raise ValueError(f"PredictedPath.{name} holds a non-finite value")

    @property
    def times(self) -> list[float]:
        return [self.t0 + (k + 1) * self.step for k in range(len(self.x))]

    @property
    def end(self) -> float:
        return self.t0 + len(self.x) * self.step


class Predictor(Protocol):
    name: str
    needs: int
    """How many recent samples :meth:`predict` needs (it uses the last ones)."""

    def predict(self, recent: History | Sequence[ShipState]) -> PredictedPath: ...


def _last(recent: History | Sequence[ShipState]) -> ShipState:
    if isinstance(recent, History):
        if not len(recent):
            raise ValueError("a prediction needs at least one sample")
        return next(iter(recent[-1:]))
    if not recent:
        raise ValueError("a prediction needs at least one sample")
    return recent[-1]


class KinematicPredictor:
    """Constant speed over ground, drift angle and rate of turn."""

    name = "kinematic"
    needs = 1

    def __init__(self, horizon: int = 30, step: float = 1.0) -> None:
        self.horizon, self.step = horizon, step

    def predict(self, recent: History | Sequence[ShipState]) -> PredictedPath:
        s = _last(recent)
        speed = math.hypot(s.u, s.v)
        course = s.psi + math.atan2(s.v, s.u)
        times = self.step * np.arange(1, self.horizon + 1)
        if abs(s.r) < 1e-6:
            xs = s.x + speed * times * math.cos(course)
            ys = s.y + speed * times * math.sin(course)
        else:
            turned = course + s.r * times
            xs = s.x + speed / s.r * (np.sin(turned) - math.sin(course))
            ys = s.y + speed / s.r * (math.cos(course) - np.cos(turned))
        psis = [wrap_angle(s.psi + s.r * t) for t in times]
        return PredictedPath(
            predictor=self.name,
            t0=s.t,
            step=self.step,
            x=xs.tolist(),
            y=ys.tolist(),
            psi=psis,
        )


class DynamicPredictor:
    """The ship's equations of motion in calm water, actuators held, integrated by RK4.

    The velocity the ship reports is over ground; in a current the model takes it for the
    velocity through the water, which is exactly what it cannot know.
    """

    name = "dynamic"
    needs = 1

    def __init__(
        self,
        params: ShipParams | None = None,
        horizon: int = 30,
        step: float = 1.0,
        dt: float = 0.5,
    ) -> None:
        self.params = params if params is not None else ShipParams()
        self.horizon, self.step = horizon, step
        self.substeps = max(1, round(step / dt))
        self.dt = step / self.substeps

    def predict(self, recent: History | Sequence[ShipState]) -> PredictedPath:
        s = _last(recent)
        state: Vector6 = (s.x, s.y, s.psi, s.u, s.v, s.r)
        xs: list[float] = []
        ys: list[float] = []
        psis: list[float] = []
        for _ in range(self.horizon):
            for _ in range(self.substeps):
                state = rk4_step(self.params, state, self.dt, s.rudder, s.rps)
            xs.append(state[0])
            ys.append(state[1])
            psis.append(wrap_angle(state[2]))
        return PredictedPath(predictor=self.name, t0=s.t, step=self.step, x=xs, y=ys, psi=psis)


# -- the learned model, served --------------------------------------------------------------


class ModelError(ValueError):
    """A model's bytes that cannot be served: the reason says why."""


def model_hash(model_bytes: bytes) -> str:
    """The SHA-256 of a model's bytes, in hex: what identifies a model version."""
    return hashlib.sha256(model_bytes).hexdigest()


class ServedModel:
    """ONNX bytes behind an onnxruntime session, checked to fit the feature layout they
    declare; thread-safe to run."""

    def __init__(self, model_bytes: bytes) -> None:
        if not model_bytes:
            raise ModelError("a model needs non-empty bytes")
        self.model_bytes = bytes(model_bytes)
        self.hash = model_hash(self.model_bytes)
        try:
            proto = onnx.load_model_from_string(self.model_bytes)
            onnx.checker.check_model(proto)
        except (DecodeError, onnx.checker.ValidationError) as exc:
            raise ModelError(f"the bytes are not a valid ONNX model: {exc}") from exc
        meta = {entry.key: entry.value for entry in proto.metadata_props}
        if SPEC_KEY not in meta:
            raise ModelError(f"the model does not declare its feature layout ({SPEC_KEY})")
        try:
            self.spec = FeatureSpec.decode(meta[SPEC_KEY])
        except (ValueError, TypeError) as exc:
            raise ModelError(f"the model's feature layout is unreadable: {exc}") from exc
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        try:
            self._session = ort.InferenceSession(
                self.model_bytes, sess_options=options, providers=["CPUExecutionProvider"]
            )
        # onnxruntime's own errors (Fail, InvalidGraph, NotImplemented...) derive from
        # Exception only; whatever it refuses is a model that cannot be served
        except Exception as exc:
            raise ModelError(f"onnxruntime refused the model: {exc}") from exc
        inputs = self._session.get_inputs()
        outputs = self._session.get_outputs()
        if [i.name for i in inputs] != [INPUT] or [o.name for o in outputs] != [OUTPUT]:
            raise ModelError(
                f"the model must take one input {INPUT!r} and give one output {OUTPUT!r}"
            )
        width = inputs[0].shape[-1]
        if width != self.spec.n_features:
            raise ModelError(
                f"the model takes {width} features, its layout says {self.spec.n_features}"
            )
        out_width = outputs[0].shape[-1]
        if out_width != self.spec.n_outputs:
            raise ModelError(
                f"the model gives {out_width} outputs, its layout says {self.spec.n_outputs}"
            )

    def run(self, rows: FloatArray) -> FloatArray:
        """The model's outputs for feature rows (n, n_features); refuses non-finite ones."""
        if rows.ndim != 2 or rows.shape[1] != self.spec.n_features:
            raise ValueError(f"features must have shape (n, {self.spec.n_features})")
        if not len(rows):
            return np.empty((0, self.spec.n_outputs))
        result = self._session.run([OUTPUT], {INPUT: rows.astype(np.float32)})[0]
        out = cast(FloatArray, np.asarray(result, dtype=np.float64))
        if out.shape != (len(rows), self.spec.n_outputs):
            raise ModelError(f"the model gave outputs of shape {out.shape}")
        if not np.isfinite(out).all():
            raise ModelError("the model gave a non-finite output")
        return out


class DataDrivenPredictor:
    """A learned model served by onnxruntime; :attr:`model_hash` names the model in use."""

    name = "data_driven"

    def __init__(self, model_bytes: bytes) -> None:
        self.model = ServedModel(model_bytes)
        self.spec = self.model.spec
        self.needs = self.spec.lags

    @property
    def model_hash(self) -> str:
        return self.model.hash

    def predict(self, recent: History | Sequence[ShipState]) -> PredictedPath:
        history = recent if isinstance(recent, History) else History.from_states(recent)
        tail = history[-self.spec.lags :]
        rows = windows(tail, self.spec, future=False)
        if len(rows) == 0:
            raise ValueError(
                f"the data-driven predictor needs the last {self.spec.lags} samples, "
                f"{self.spec.sample_period} s apart"
            )
        row = int(rows[-1])
        out = self.model.run(features(tail, rows[-1:], self.spec))[0]
        t, x, y, psi = (float(tail.data[row, k]) for k in range(4))
        xs, ys, psis = to_earth(out, x, y, psi, self.spec)
        return PredictedPath(
            predictor=self.name,
            t0=t,
            step=self.spec.sample_period,
            x=xs.tolist(),
            y=ys.tolist(),
            psi=psis.tolist(),
            model_hash=self.model.hash,
        )


# -- scoring --------------------------------------------------------------------------------


def _error_against(
    path: PredictedPath, t: FloatArray, x: FloatArray, y: FloatArray, horizon_s: float | None
) -> float | None:
    times = np.array(path.times)
    if horizon_s is not None:
        times = times[times <= path.t0 + horizon_s + 1e-9]
    n = len(times)
    if not n or not len(t) or times[0] < t[0] - 1e-9 or times[-1] > t[-1] + 1e-9:
        return None
    dx = np.array(path.x[:n]) - np.interp(times, t, x)
    dy = np.array(path.y[:n]) - np.interp(times, t, y)
    return float(np.mean(np.hypot(dx, dy)))


def path_error(
    path: PredictedPath, history: History, horizon_s: float | None = None
) -> float | None:
    """Mean distance (m) between the path's positions and the ship's actual ones (linearly
    interpolated between samples), or None while the history does not cover the path."""
    return _error_against(path, history.t, history.column("x"), history.column("y"), horizon_s)


class ScoreTracker:
    """A predictor's score: the mean position error of its last ``window`` matured paths.

    Feed it every path the predictor gives (:meth:`add`) and every sample of what happened
    (:meth:`observe`); a path matures when the ship has been seen past its last point (or
    past ``horizon_s`` after its start, when that is given, to score a shorter horizon).
    """

    def __init__(self, window: int = 20, *, horizon_s: float | None = None) -> None:
        if window < 1:
            raise ValueError("ScoreTracker.window must be at least 1")
        self.window = window
        self.horizon_s = horizon_s
        self._pending: deque[PredictedPath] = deque()
        self._seen: deque[tuple[float, float, float]] = deque()
        self._errors: deque[float] = deque(maxlen=window)
        self.matured = 0

    def _due(self, path: PredictedPath) -> float:
        return path.end if self.horizon_s is None else min(path.end, path.t0 + self.horizon_s)

    def add(self, path: PredictedPath) -> None:
        self._pending.append(path)

    def observe(self, state: ShipState) -> float | None:
        """Record where the ship was at ``state.t``; returns the (possibly new) score."""
        if self._seen and state.t <= self._seen[-1][0]:
            raise ValueError("ScoreTracker.observe needs samples in increasing time")
        self._seen.append((state.t, state.x, state.y))
        ready = [p for p in self._pending if self._due(p) <= state.t + 1e-9]
        if ready:
            seen = np.array(self._seen)
            for path in ready:
                self._pending.remove(path)
                error = _error_against(path, seen[:, 0], seen[:, 1], seen[:, 2], self.horizon_s)
                if error is not None:
                    self._errors.append(error)
                    self.matured += 1
        oldest = min((p.t0 for p in self._pending), default=state.t)
        while len(self._seen) > 1 and self._seen[1][0] <= oldest:
            self._seen.popleft()
        return self.score

    @property
    def score(self) -> float | None:
        """Mean position error (m) over the window, None before any path has matured."""
        if not self._errors:
            return None
        return float(np.mean(self._errors))


def replay(predictor: Predictor, history: History, *, every: int = 1) -> list[PredictedPath]:
    """The predictor's path at every ``every``-th sample that has enough samples before it."""
    paths = []
    for row in range(predictor.needs - 1, len(history), every):
        tail = history[row + 1 - predictor.needs : row + 1]
        paths.append(predictor.predict(tail))
    return paths


def replay_error(
    predictor: Predictor, history: History, *, every: int = 1, horizon_s: float | None = None
) -> float:
    """The mean :func:`path_error` of the predictor replayed over ``history``."""
    errors = [
        error
        for path in replay(predictor, history, every=every)
        if path.end <= history.t[-1] + 1e-9
        and (error := path_error(path, history, horizon_s)) is not None
    ]
    if not errors:
        raise ValueError("the history is too short for any path to mature")
    return float(np.mean(errors))
