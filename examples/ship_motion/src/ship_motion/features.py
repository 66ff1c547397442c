"""What the data-driven predictor sees and what it predicts, shared by training and serving.

A window of a :class:`~ship_motion.physics.History` is turned into one row of features: the
velocities, yaw rate and actuators of the last ``lags`` samples, and the cosine and sine of
the present heading (the weather comes from fixed directions in the earth frame, so its
effect on the ship depends on where the ship points). The prediction is the path over the
next ``horizon`` samples written in the frame of the present pose: forward and sideways
displacement and the change of heading at each future sample. Working in that frame keeps
the model independent of where on the chart the ship is.
"""

from __future__ import annotations

import math
from typing import cast

import msgspec
import numpy as np
from numpy.typing import NDArray

from .physics import _S, COLUMNS, FloatArray, History

__all__ = [
    "FeatureSpec",
    "feature_names",
    "features",
    "futures",
    "targets",
    "to_earth",
    "windows",
]

IntArray = NDArray[np.int64]

_PER_LAG = ("u", "v", "r", "rudder", "rps")
_LAGGED = [COLUMNS.index(name) for name in _PER_LAG]
_T, _X, _Y, _PSI = (COLUMNS.index(name) for name in ("t", "x", "y", "psi"))


class FeatureSpec(_S, frozen=True, kw_only=True):
    """The layout a model was trained for; it travels inside the model's bytes."""

    lags: int = 4
    """Samples of the past (the present one included) whose motion is fed in."""
    horizon: int = 30
    """Samples predicted ahead."""
    sample_period: float = 1.0
    """Seconds between samples."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 1 <= self.lags <= 60:
            raise ValueError(f"FeatureSpec.lags is {self.lags}: it must be within [1, 60]")
        if not 1 <= self.horizon <= 600:
            raise ValueError(f"FeatureSpec.horizon is {self.horizon}: it must be within [1, 600]")
        if not 0 < self.sample_period <= 60:
            raise ValueError(
                f"FeatureSpec.sample_period is {self.sample_period}: it must be in (0, 60]"
            )

    @property
    def n_features(self) -> int:
        return len(_PER_LAG) * self.lags + 2

    @property
    def n_outputs(self) -> int:
        return 3 * self.horizon

    def encode(self) -> str:
        return msgspec.json.encode(self).decode()

    @classmethod
    def decode(cls, text: str | bytes) -> FeatureSpec:
        return msgspec.json.decode(text, type=cls)


def feature_names(spec: FeatureSpec) -> list[str]:
    names = [f"{name}[-{lag}]" for lag in range(spec.lags) for name in _PER_LAG]
    return [*names, "cos(psi)", "sin(psi)"]


def windows(history: History, spec: FeatureSpec, *, future: bool) -> IntArray:
    """The rows ``i`` that have ``lags`` evenly spaced samples up to and including ``i``
    (and, with ``future``, ``horizon`` evenly spaced samples after it)."""
    n = len(history)
    need_after = spec.horizon if future else 0
    if n < spec.lags + need_after:
        return np.empty(0, dtype=np.int64)
    gaps = np.abs(np.diff(history.t) - spec.sample_period) > 1e-6 * spec.sample_period
    # bad[k] counts the broken intervals among the first k intervals
    bad = np.concatenate([[0], np.cumsum(gaps)])
    rows = np.arange(spec.lags - 1, n - need_after)
    first = rows - (spec.lags - 1)
    last = rows + need_after
    ok = bad[last] - bad[first] == 0
    return cast(IntArray, rows[ok])


def features(history: History, rows: IntArray, spec: FeatureSpec) -> FloatArray:
    """One feature row per index in ``rows`` (see :func:`feature_names`)."""
    data = history.data
    blocks = [data[rows - lag][:, _LAGGED] for lag in range(spec.lags)]
    psi = data[rows, _PSI]
    out = np.concatenate([*blocks, np.cos(psi)[:, None], np.sin(psi)[:, None]], axis=1)
    return np.ascontiguousarray(out, dtype=np.float64)


def futures(history: History, rows: IntArray, spec: FeatureSpec) -> FloatArray:
    """The actual displacements after each row, in the row's frame: shape (len(rows), 3, H)
    holding forward metres, starboard metres and the heading's change in radians."""
    data = history.data
    psi = np.unwrap(data[:, _PSI])
    ahead = rows[:, None] + np.arange(1, spec.horizon + 1)[None, :]
    dx = data[ahead, _X] - data[rows, _X][:, None]
    dy = data[ahead, _Y] - data[rows, _Y][:, None]
    c = np.cos(psi[rows])[:, None]
    s = np.sin(psi[rows])[:, None]
    forward = c * dx + s * dy
    side = -s * dx + c * dy
    turn = psi[ahead] - psi[rows][:, None]
    return np.stack([forward, side, turn], axis=1)


def targets(history: History, rows: IntArray, spec: FeatureSpec) -> FloatArray:
    """:func:`futures` flattened the way a model's output is laid out: H forward values,
    then H starboard values, then H heading changes."""
    return futures(history, rows, spec).reshape(len(rows), spec.n_outputs)


def to_earth(
    outputs: FloatArray, x: float, y: float, psi: float, spec: FeatureSpec
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A model's output row as earth-frame positions and headings after the pose (x, y, psi)."""
    forward = outputs[: spec.horizon]
    side = outputs[spec.horizon : 2 * spec.horizon]
    turn = outputs[2 * spec.horizon :]
    c, s = math.cos(psi), math.sin(psi)
    xs = x + c * forward - s * side
    ys = y + s * forward + c * side
    headings = np.array([math.remainder(psi + d, 2.0 * math.pi) for d in turn])
    return xs, ys, headings
