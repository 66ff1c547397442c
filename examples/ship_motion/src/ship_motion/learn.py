"""Training the data-driven predictor, exporting it to ONNX, and judging a candidate.

The model is a one-hidden-layer network whose hidden layer is fixed and random (tanh of a
random projection of the standardised features) and whose read-out, from the standardised
features and the hidden units together, is fitted in closed form by ridge regression. The
random layer gives it the curvature of a turn, the direct path keeps it close to a linear
model where data is thin, and the fit is one linear solve: a window of a few hundred
samples trains in milliseconds on one core, deterministically for a given seed.

:func:`to_onnx` writes the same network as an ONNX graph with ``onnx.helper`` (Sub, Mul,
MatMul, Add, Tanh, Concat) and stores the :class:`~ship_motion.features.FeatureSpec` in the
model's metadata, so the bytes alone say how to feed them. :func:`evaluate` replays recorded
history through any candidate's bytes: the gate's measure of a model. :func:`bad_model`
makes a model that serves fine and predicts nonsense, for showing the gate rejects it.

Everything here is a pure function of its arguments, safe to call from a worker thread.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from .features import FeatureSpec, features, futures, targets, windows
from .physics import FloatArray, History
from .predict import INPUT, OUTPUT, SPEC_KEY, ServedModel

__all__ = [
    "MIN_SAMPLES",
    "RandomFeatureModel",
    "TrainingError",
    "bad_model",
    "errors",
    "evaluate",
    "to_onnx",
    "train",
    "train_onnx",
]

MIN_SAMPLES = 60
"""The fewest complete windows (features and the full horizon after) :func:`train` accepts."""

OPSET = 17
IR_VERSION = 8


class TrainingError(ValueError):
    """The history cannot train a model: the reason says why."""


@dataclass(frozen=True, eq=False)
class RandomFeatureModel:
    """The network in numpy: ``y = [z, tanh(z W1 + b1)] W2 + b2``, ``z = (x - mean) * scale``."""

    spec: FeatureSpec
    mean: FloatArray
    scale: FloatArray
    w1: FloatArray
    b1: FloatArray
    w2: FloatArray
    b2: FloatArray

    def hidden(self, rows: FloatArray) -> FloatArray:
        z = (rows - self.mean) * self.scale
        return np.concatenate([z, np.tanh(z @ self.w1 + self.b1)], axis=1)

    def predict(self, rows: FloatArray) -> FloatArray:
        """Outputs for feature rows, in float64 (the ONNX graph computes them in float32)."""
        return self.hidden(rows) @ self.w2 + self.b2


def train(
    history: History,
    *,
    spec: FeatureSpec | None = None,
    hidden: int = 96,
    ridge: float = 1e-2,
    seed: int = 0,
) -> RandomFeatureModel:
    """Fit a model on every complete window of ``history``.

    ``hidden`` is the number of random units, ``seed`` draws them; ``ridge`` is the penalty
    on the read-out's weights relative to the mean square of its (unit-scale) inputs.
    """
    spec = spec if spec is not None else FeatureSpec()
    if hidden < 1:
        raise TrainingError(f"hidden is {hidden}: a model needs at least one hidden unit")
    if not ridge > 0:
        raise TrainingError(f"ridge is {ridge}: it must be above 0")
    rows = windows(history, spec, future=True)
    if len(rows) < MIN_SAMPLES:
        raise TrainingError(
            f"the history holds {len(rows)} complete windows of {spec.lags} + {spec.horizon} "
            f"samples, {spec.sample_period} s apart; training needs at least {MIN_SAMPLES}"
        )
    x = features(history, rows, spec)
    y = targets(history, rows, spec)
    mean = x.mean(axis=0)
    sd = x.std(axis=0)
    scale = np.where(sd > 1e-9, 1.0 / np.where(sd > 1e-9, sd, 1.0), 0.0)
    rng = np.random.default_rng(seed)
    n_in = spec.n_features
    w1 = rng.normal(0.0, 1.0 / np.sqrt(n_in), size=(n_in, hidden))
    b1 = rng.uniform(-1.0, 1.0, size=hidden)
    partial = RandomFeatureModel(
        spec, mean, scale, w1, b1, np.zeros((n_in + hidden, spec.n_outputs)), np.zeros(0)
    )
    phi = partial.hidden(x)
    phi_mean = phi.mean(axis=0)
    y_mean = y.mean(axis=0)
    pc = phi - phi_mean
    n = len(rows)
    gram = pc.T @ pc / n + ridge * np.eye(phi.shape[1])
    w2 = np.linalg.solve(gram, pc.T @ (y - y_mean) / n)
    b2 = y_mean - phi_mean @ w2
    return RandomFeatureModel(spec, mean, scale, w1, b1, w2, b2)


def to_onnx(model: RandomFeatureModel, *, name: str = "ship_motion") -> bytes:
    """The model as ONNX bytes (float32), its feature layout in the metadata."""
    spec = model.spec

    def const(array: FloatArray, label: str) -> TensorProto:
        return numpy_helper.from_array(np.ascontiguousarray(array, dtype=np.float32), label)

    initializers = [
        const(model.mean[None, :], "mean"),
        const(model.scale[None, :], "scale"),
        const(model.w1, "w1"),
        const(model.b1[None, :], "b1"),
        const(model.w2, "w2"),
        const(model.b2[None, :], "b2"),
    ]
    nodes = [
        helper.make_node("Sub", [INPUT, "mean"], ["centred"]),
        helper.make_node("Mul", ["centred", "scale"], ["z"]),
        helper.make_node("MatMul", ["z", "w1"], ["projected"]),
        helper.make_node("Add", ["projected", "b1"], ["preactivation"]),
        helper.make_node("Tanh", ["preactivation"], ["activation"]),
        helper.make_node("Concat", ["z", "activation"], ["phi"], axis=1),
        helper.make_node("MatMul", ["phi", "w2"], ["readout"]),
        helper.make_node("Add", ["readout", "b2"], [OUTPUT]),
    ]
    graph = helper.make_graph(
        nodes,
        name,
        [helper.make_tensor_value_info(INPUT, TensorProto.FLOAT, ["n", spec.n_features])],
        [helper.make_tensor_value_info(OUTPUT, TensorProto.FLOAT, ["n", spec.n_outputs])],
        initializer=initializers,
    )
    proto = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        ir_version=IR_VERSION,
        producer_name="rap-ship-motion",
        doc_string="Ship path predictor: random tanh features with a ridge read-out.",
    )
    helper.set_model_props(proto, {SPEC_KEY: spec.encode()})
    onnx.checker.check_model(proto)
    return bytes(proto.SerializeToString())


def train_onnx(
    history: History,
    *,
    spec: FeatureSpec | None = None,
    hidden: int = 96,
    ridge: float = 1e-2,
    seed: int = 0,
) -> bytes:
    """:func:`train` then :func:`to_onnx`."""
    return to_onnx(train(history, spec=spec, hidden=hidden, ridge=ridge, seed=seed))


def errors(model_bytes: bytes, history: History) -> FloatArray:
    """The candidate's mean position error (m) over the horizon, one per complete window of
    ``history``. Raises :class:`~ship_motion.predict.ModelError` for bytes that cannot be
    served or give non-finite predictions."""
    served = ServedModel(model_bytes)
    spec = served.spec
    rows = windows(history, spec, future=True)
    if not len(rows):
        raise ValueError(
            f"the history holds no complete window of {spec.lags} + {spec.horizon} samples"
        )
    out = served.run(features(history, rows, spec))
    predicted = out.reshape(len(rows), 3, spec.horizon)
    actual = futures(history, rows, spec)
    # both are in the frame of the pose at the window's start: a rotation keeps distances
    miss = np.hypot(predicted[:, 0] - actual[:, 0], predicted[:, 1] - actual[:, 1])
    return np.asarray(miss.mean(axis=1), dtype=np.float64)


def evaluate(model_bytes: bytes, history: History) -> float:
    """Replay ``history`` through the candidate: its mean position error in metres over
    every complete window and every step of the horizon (lower is better)."""
    return float(errors(model_bytes, history).mean())


def bad_model(history: History, *, spec: FeatureSpec | None = None, seed: int = 0) -> bytes:
    """A model that loads and serves like a good one but predicts the ship sailing
    backwards: trained on ``history``, then every output negated."""
    good = train(history, spec=spec, seed=seed)
    reversed_ = RandomFeatureModel(
        good.spec, good.mean, good.scale, good.w1, good.b1, -good.w2, -good.b2
    )
    return to_onnx(reversed_, name="ship_motion_reversed")
