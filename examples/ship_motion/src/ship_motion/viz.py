"""A Rerun recording of one ship-motion run: actual against predicted paths, and when the
models changed (``python -m ship_motion.eval --rerun``; open it with ``rerun FILE.rrd``).

Entities (timeline ``sim``, seconds of sim time; positions in metres, east right, north up):

    sea/actual                    where the ship has been
    sea/ship                      where it is
    sea/predicted/data_driven     the data-driven model's path, when the display shows it
    sea/predicted/fallback        the physics path the display falls back to (the safe state)
    error/display                 the shown path's mean error once it has matured, m
    events                        the front, anomalies, models the display serves; at the end,
                                  the verdicts and the versions Execute pinned
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .physics import History
from .predict import PredictedPath, path_error

if TYPE_CHECKING:
    from .eval import Observer

__all__ = ["RerunFileError", "ShipRerun"]


class RerunFileError(ValueError):
    """The recording file cannot be written; the message names it and says what to do."""


def _en(x: Any, y: Any) -> list[tuple[float, float]]:
    """North/east to the viewer's (east, north)."""
    return [(float(e), float(n)) for n, e in zip(x, y, strict=True)]


class ShipRerun:
    def __init__(self, *, path: str, seed: int) -> None:
        import rerun as rr  # heavy: loaded only when a recording is asked for

        self.rr = rr
        app = "rap_ship_motion"
        self.rec = rr.RecordingStream(app, recording_id=f"{app}-{seed}")
        try:
            self.rec.save(path)
        except RuntimeError as exc:
            raise RerunFileError(
                f"{path}: cannot write the Rerun recording ({exc}) - give a file path in an "
                "existing, writable directory"
            ) from None

    def log_run(self, truth: History, obs: Observer, *, onset: float) -> None:
        rr, rec = self.rr, self.rec
        xs, ys = truth.column("x"), truth.column("y")
        events: dict[float, list[str]] = {}
        for t in obs.anomalies:
            events.setdefault(t, []).append("anomaly: the data-driven score stayed too high")
        events.setdefault(onset, []).append("weather front sets in")
        shown_hash = ""
        for k, t in enumerate(truth.t):
            ts = float(t)
            rec.set_time("sim", duration=ts)
            rec.log("sea/ship", rr.Points2D(_en([xs[k]], [ys[k]]), radii=8.0))
            if k % 10 == 0:
                rec.log("sea/actual", rr.LineStrips2D([_en(xs[: k + 1], ys[: k + 1])]))
            p = obs.display.get(ts)
            if p is not None:
                where = "fallback" if p.fallback else "data_driven"
                other = "data_driven" if p.fallback else "fallback"
                rec.log(f"sea/predicted/{where}", rr.LineStrips2D([_en(p.x, p.y)]))
                rec.log(f"sea/predicted/{other}", rr.Clear(recursive=False))
                ours = PredictedPath(
                    predictor=p.predictor.value, t0=p.t0, step=p.step, x=p.x, y=p.y, psi=p.psi
                )
                err = path_error(ours, truth)
                if err is not None:
                    rec.log("error/display", rr.Scalars(err))
                if not p.fallback and p.model_hash != shown_hash:
                    shown_hash = p.model_hash
                    events.setdefault(ts, []).append(
                        f"display serves model v{p.model_version} ({p.model_hash[:12]})"
                    )
            for line in events.get(ts, []):
                rec.log("events", rr.TextLog(line))
        for v in obs.verdicts:  # verdicts carry no sim time: logged at the end
            word = "approved" if v.approved else f"rejected ({v.reason})"
            rec.log("events", rr.TextLog(f"candidate v{v.version} {word}"))
        for m in obs.executed:
            rec.log("events", rr.TextLog(f"execute pinned v{m.version} ({m.model_hash[:12]})"))

    def close(self) -> None:
        self.rec.flush()
