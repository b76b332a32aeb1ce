"""The smoother: ISAM2 over the whole history (the paper) or GTSAM's incremental fixed-lag
smoother (bounded cost per frame), the factors and values waiting for its next update, the final
estimates of frames it has let go, and re-anchoring when GTSAM fails.

GTSAM can fail an update (an indeterminant linear system, a key it lost after a failed Cholesky
step): the smoother then starts afresh from a tight prior at the last good estimate and re-adds
the failed frames on top (counted as a recovery), so a drive never ends in an exception.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from . import factors
from .config import Backend, FusionConfig, StateModel
from .counters import Counters
from .factors import X
from .track import Track

log = logging.getLogger(__name__)

#: ISAM2's relinearisation threshold (tangent-space step). Source: GTSAM's examples.
RELINEARIZE_THRESHOLD = 0.01

#: Yaw σ of the prior that re-anchors a fresh smoother after GTSAM failed. Unit: deg. Source: robustness.
REANCHOR_YAW_SIGMA_DEG = 2.0

#: x/y σ of that prior. Unit: m. Source: robustness.
REANCHOR_SIGMA_M = 0.5


class _Backend:
    """ISAM2 over the whole history, or GTSAM's incremental fixed-lag smoother."""

    def __init__(self, cfg: FusionConfig) -> None:
        params = gtsam.ISAM2Params()
        params.setFactorization(cfg.factorization.value)
        params.setRelinearizeThreshold(RELINEARIZE_THRESHOLD)
        params.relinearizeSkip = 1
        self.fixed_lag = cfg.backend is Backend.fixed_lag
        # marginalised factors free their slots: reuse them, or ISAM2's factor list grows forever
        params.findUnusedFactorSlots = self.fixed_lag
        self.s = gtsam.IncrementalFixedLagSmoother(cfg.lag_s, params) if self.fixed_lag else gtsam.ISAM2(params)

    def update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, float]) -> None:
        if self.fixed_lag:
            self.s.update(graph, values, stamps)  # type: ignore[arg-type, call-overload]
        else:
            self.s.update(graph, values)

    def pose(self, key: int) -> gtsam.Pose3:
        return self.s.calculateEstimatePose3(key)

    def covariance(self, key: int) -> np.ndarray:
        return self.s.marginalCovariance(key)

    def keys(self) -> list[int]:
        return list(self.s.calculateEstimate().keys())


@dataclass
class Pending:
    """Factors and values waiting for the next update."""

    graph: gtsam.NonlinearFactorGraph = field(default_factory=gtsam.NonlinearFactorGraph)
    values: gtsam.Values = field(default_factory=gtsam.Values)
    stamps: dict = field(default_factory=dict)
    keys: list = field(default_factory=list)


class Smoother:
    """The backend and its bookkeeping over the frames of a :class:`~mapfusion.track.Track`.

    ``between_for(k)`` builds the odometry factor into frame k (re-anchoring re-adds them);
    ``first_pose()`` is frame 0's pose when there is no better anchor.
    """

    def __init__(self, cfg: FusionConfig, track: Track, counters: Counters,
                 between_for: Callable[[int], gtsam.NonlinearFactor], first_pose: Callable[[], gtsam.Pose3]) -> None:
        self.cfg = cfg
        self.track = track
        self.counters = counters
        self._between_for = between_for
        self._first_pose = first_pose
        self.backend = _Backend(cfg)
        self.pending = Pending()
        self.last_key = -1
        self.last_updated_key = -1
        self.last_updated_pose: gtsam.Pose3 | None = None
        self.smoothed: dict[int, gtsam.Pose3 | None] = {}  # None: a frame that never had an estimate
        self.smoothed_upto = -1  # every frame up to this one has its final smoothed estimate
        self.guess: dict[int, gtsam.Pose3] = {}  # a restart's estimates of past frames (until final)

    # -------------------------------------------------------------- building
    def add(self, factor: gtsam.NonlinearFactor) -> None:
        self.pending.graph.add(factor)

    def insert(self, k: int, pose: gtsam.Pose3) -> None:
        self.pending.values.insert(X(k), pose)
        self.pending.stamps[X(k)] = self.track.t[k]
        self.pending.keys.append(k)
        self.last_key = k

    def seed(self, poses: list[gtsam.Pose3]) -> None:
        """Frames 0 … len(poses) - 1 final at ``poses`` (the initialisation's batch before its last frame)."""
        for k, pose in enumerate(poses):
            self.smoothed[k] = pose
        self.smoothed_upto = len(poses) - 1

    def restart(self) -> None:
        """A fresh backend, nothing pending, no updated frame (a re-localisation follows)."""
        self.backend = _Backend(self.cfg)
        self.pending = Pending()
        self.guess = {}
        self.last_updated_key, self.last_updated_pose = -1, None

    def restart_from(self, k0: int, pose: gtsam.Pose3, noise, step_for: Callable[[int], gtsam.Pose3]) -> None:
        """Start afresh at frame ``k0`` (a prior on ``pose`` with ``noise``; the frames before keep their
        causal estimates as final) and re-add the frames since, each by its step (a re-localisation). Frames
        from k0 on that were already final (a correction reaching back into the initialisation's batch) are
        estimated afresh."""
        self.finalise_upto(k0 - 1)
        for k in range(k0, self.smoothed_upto + 1):
            self.smoothed.pop(k, None)
        self.smoothed_upto = min(self.smoothed_upto, k0 - 1)
        self.restart()
        self.add(factors.pose_prior(k0, pose, noise))
        online, last = self.track.online, len(self.track) - 1
        for k in range(k0, last + 1):
            if k > k0:
                self.add(self._between_for(k))
                pose = pose.compose(step_for(k))
            self.insert(k, pose)
            # the frames before the last keep their causal estimate (the online error is causal); the guess
            # stands in as final for those the fixed-lag smoother marginalises in its first update
            self.guess[k] = pose
            if k == last or online[k] is None:
                online[k] = pose

    def finalise_upto(self, k: int) -> None:
        """Frames up to k keep their causal estimate as final where they have none yet."""
        online = self.track.online
        for j in range(self.smoothed_upto + 1, k + 1):
            if online[j] is not None:
                self.smoothed.setdefault(j, online[j])
        self.smoothed_upto = max(self.smoothed_upto, k)

    # -------------------------------------------------------------- reading
    def pose(self, k: int) -> gtsam.Pose3:
        return self.backend.pose(X(k))

    def covariance(self, k: int) -> np.ndarray:
        return self.backend.covariance(X(k))

    def position_sigmas(self) -> tuple[float, float, float] | None:
        """The latest updated frame's largest positional σ and its σ across the vehicle (m), and its yaw σ (rad);
        None when GTSAM has no marginal for it (e.g. ISAM2 re-anchored after a failed Cholesky update and the key
        is not in the new Bayes tree: the next check will have one)."""
        try:
            cov = self.covariance(self.last_updated_key)
        except (RuntimeError, IndexError):
            return None
        xy = cov[3:5, 3:5]
        return (math.sqrt(max(float(np.linalg.eigvalsh(xy).max()), 0.0)), math.sqrt(max(float(xy[1, 1]), 0.0)),
                math.sqrt(max(float(cov[2, 2]), 0.0)))

    def poses(self) -> dict[int, gtsam.Pose3 | None]:
        """Final estimates of the frames let go, then the backend's current ones."""
        out = dict(self.smoothed)
        for key in self.backend.keys():
            out[gtsam.Symbol(key).index()] = self.backend.pose(key)
        return out

    # -------------------------------------------------------------- updating
    def update(self) -> bool:
        """Hand the pending factors to the backend; False when nothing was pending."""
        p = self.pending
        if p.graph.size() == 0 and p.values.size() == 0:
            return False
        try:
            if self.backend.fixed_lag and self.last_updated_key >= 0:
                self._keep_leaving(p)
            self.backend.update(p.graph, p.values, p.stamps)
            # a second pass lets ISAM2 relinearise around the new solution
            self.backend.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {})
            latest = self.last_key
            pose = self.backend.pose(X(latest))
            self.last_updated_key, self.last_updated_pose = latest, pose
            self.track.online[latest] = pose
        except (RuntimeError, IndexError) as exc:  # IndeterminantLinearSystem, std::out_of_range and the like
            self.counters.recoveries += 1
            log.warning("GTSAM failed (%s): re-anchoring at the last good estimate",
                        (str(exc).strip().splitlines() or [type(exc).__name__])[0])
            self._reanchor(p)
        self.counters.updates += 1
        self.pending = Pending()
        return True

    def _keep_leaving(self, p: Pending) -> None:
        """Store the final estimate of the frames the fixed-lag window is about to marginalise."""
        t = self.track.t
        t_new = max(p.stamps.values()) if p.stamps else t[self.last_key]
        horizon = t_new - self.cfg.lag_s
        for k in range(self.smoothed_upto + 1, self.last_updated_key + 1):
            if t[k] >= horizon:
                break
            guess = self.guess.pop(k, None)
            try:
                self.smoothed[k] = self.backend.pose(X(k))
            except (RuntimeError, IndexError):  # already marginalised
                self.smoothed[k] = guess if guess is not None else self.track.online[k]
            self.smoothed_upto = k

    def _reanchor(self, failed: Pending) -> None:
        """A fresh backend: a tight prior at the last good estimate, then the failed frames on it."""
        cfg, online = self.cfg, self.track.online
        anchor_k = self.last_updated_key
        anchor = self.last_updated_pose
        if anchor is None:
            anchor_k = min(failed.keys) - 1 if failed.keys else self.last_key
            anchor = online[anchor_k] if anchor_k >= 0 else None
            if anchor is None:
                anchor = self._first_pose()
        for k in range(self.smoothed_upto + 1, anchor_k + 1):
            self.smoothed.setdefault(k, online[k])
        self.smoothed_upto = max(self.smoothed_upto, anchor_k)
        self.backend = _Backend(cfg)
        g = gtsam.NonlinearFactorGraph()
        v = gtsam.Values()
        sig = factors.pose_sigmas(StateModel.planar, math.radians(REANCHOR_YAW_SIGMA_DEG), REANCHOR_SIGMA_M)
        g.add(factors.pose_prior(anchor_k, anchor, factors.diagonal(sig)))
        v.insert(X(anchor_k), anchor)
        stamps = {X(anchor_k): self.track.t[anchor_k]}
        for k in failed.keys:
            if k <= anchor_k:
                continue
            g.add(self._between_for(k))
            guess = online[k]
            v.insert(X(k), guess if guess is not None else anchor)
            stamps[X(k)] = self.track.t[k]
        try:
            self.backend.update(g, v, stamps)
            latest = max([anchor_k] + [k for k in failed.keys if k > anchor_k])
            self.last_updated_key, self.last_updated_pose = latest, self.backend.pose(X(latest))
        except (RuntimeError, IndexError):
            log.error("re-anchoring failed too; continuing from the odometry")
