"""Streaming the engine's output: frames are handed out once final and then forgotten, so the
memory of :class:`~mapfusion.engine.MapFusion` stays flat over a drive of any length."""

from __future__ import annotations

from collections.abc import Callable

import gtsam

from .config import FusionConfig
from .gps_gate import RELOCALISE_WINDOW_S
from .initialisation import SCALE_REFIT_WINDOW_S

#: ``on_final(t, online, smoothed)``: a frame's time, its causal estimate and its smoothed pose
#: (either None where the engine has none: before initialisation).
OnFinal = Callable[[float, "gtsam.Pose3 | None", "gtsam.Pose3 | None"], None]

#: Frames are held at least this long after they are made: longer than any window that looks back
#: (the smoother's lag, the scale refit, a GPS re-localisation's run of fixes).
MIN_HISTORY_S = 600.0
#: Frames are let go in batches (dropping from the front of a list costs its length).
BATCH_FRAMES = 500


def history_s(cfg: FusionConfig) -> float:
    """How long a frame is held before it is handed out and forgotten."""
    return max(MIN_HISTORY_S, 2.0 * SCALE_REFIT_WINDOW_S, 4.0 * cfg.lag_s, 4.0 * RELOCALISE_WINDOW_S)


class Release:
    """Hands out the frames that are final (the smoother let them go) and older than the history,
    in frame order, exactly as :meth:`MapFusion.online_estimates` and :meth:`MapFusion.trajectory`
    would give them at the end, then drops them from the engine's track. Without ``on_final`` it
    does nothing (the engine keeps every frame)."""

    def __init__(self, cfg: FusionConfig, on_final: OnFinal | None) -> None:
        self.on_final = on_final
        self.history_s = history_s(cfg)

    def step(self, engine) -> None:
        """After each frame: release what is old and final, a batch at a time. (Not with ISAM2 over
        the whole history: it refines every frame to the end, so none is final before it.)"""
        track, sm = engine.track, engine.smoother
        if self.on_final is None or sm is None or not sm.backend.fixed_lag:
            return
        upto = track.first
        horizon = track.t[-1] - self.history_s
        while upto <= sm.smoothed_upto and track.t[upto] < horizon:
            upto += 1
            if upto == len(track):
                break
        if upto - track.first >= BATCH_FRAMES:
            self._hand_out(engine, upto)

    def finish(self, engine) -> None:
        """At the end: every frame still held, with the smoother's final poses."""
        track = engine.track
        if self.on_final is None:  # not streaming: the engine keeps everything
            return
        if engine.smoother is None:
            for _, t in list(track.t.held()):
                self.on_final(t, None, None)
        else:
            smoothed = engine.trajectory()
            for k, t in list(track.t.held()):
                self.on_final(t, track.online[k], smoothed.get(t))
        track.drop_before(len(track))

    def _hand_out(self, engine, upto: int) -> None:
        track, sm = engine.track, engine.smoother
        assert self.on_final is not None
        for k in range(track.first, upto):
            online = track.online[k]
            # as trajectory() has it: the smoother's final pose, else (never held) the causal one
            self.on_final(track.t[k], online, sm.smoothed.pop(k) if k in sm.smoothed else online)
        track.drop_before(upto)
