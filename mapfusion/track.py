"""The odometry frames the engine has seen: times, raw poses in the odometry's own frame, the
relative motions, and each frame's causal estimate in the map frame.

Raw poses are the odometry as given (unscaled), composed from the relative motions; once the
planar state levels the odometry frame they are stored levelled. :class:`Alignment` (from the GPS
initialisation) takes a raw pose into the map frame.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import gtsam
import numpy as np

from .config import StateModel


def level(p: gtsam.Pose3) -> gtsam.Pose3:
    """The pose with roll and pitch removed and z = 0 (a ground vehicle on the map plane)."""
    yaw = p.rotation().yaw()
    return gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(p.x(), p.y(), 0.0))


def planar_step(prev_odo: gtsam.Pose3, cur_odo: gtsam.Pose3) -> gtsam.Pose3:
    """Relative motion projected on the horizontal plane with the odometry's own attitude:
    the world displacement rotated by the previous yaw only; dz, roll and pitch dropped."""
    d = cur_odo.translation() - prev_odo.translation()
    y0 = prev_odo.rotation().yaw()
    y1 = cur_odo.rotation().yaw()
    c, s = math.cos(y0), math.sin(y0)
    return gtsam.Pose3(gtsam.Rot3.Yaw(y1 - y0), gtsam.Point3(c * d[0] + s * d[1], -s * d[0] + c * d[1], 0.0))


@dataclass(frozen=True)
class Alignment:
    """The odometry frame in the map frame: scale, then a rotation by ``rot_rad`` about z, then a
    shift by ``trans_m`` (x, y)."""

    scale: float
    scale_sigma: float
    rot_rad: float
    trans_m: np.ndarray


class Track:
    """Odometry frames in time order, and their causal estimates (None before initialisation)."""

    def __init__(self, state: StateModel, nominal_period_s: float) -> None:
        self.state = state
        self.nominal_period_s = nominal_period_s
        self.t: list[float] = []
        self.raw: list[gtsam.Pose3] = []  # raw absolute odometry poses (levelled once level is set)
        self.rel: list[gtsam.Pose3] = []  # raw relative motion into each frame (identity for the first)
        self.online: list[gtsam.Pose3 | None] = []
        self.level_rot: gtsam.Pose3 | None = None
        self._odo_abs = gtsam.Pose3()

    def __len__(self) -> int:
        return len(self.t)

    def append(self, t: float, rel: gtsam.Pose3) -> np.ndarray:
        """A new frame from its relative motion; returns its raw (unlevelled) position."""
        first = not self.t
        self._odo_abs = self._odo_abs if first else self._odo_abs.compose(rel)
        self.t.append(t)
        self.raw.append(self.level_rot.compose(self._odo_abs) if self.level_rot is not None else self._odo_abs)
        self.rel.append(gtsam.Pose3() if first else rel)
        self.online.append(None)
        return self._odo_abs.translation()

    def frame_at(self, t: float) -> int:
        """Index of the frame nearest in time (bisect: the frame list only grows)."""
        i = min(bisect.bisect_left(self.t, t), len(self.t) - 1)
        if i > 0 and abs(self.t[i - 1] - t) <= abs(self.t[i] - t):
            i -= 1
        return i

    def raw_at(self, t: float) -> gtsam.Pose3:
        return self.raw[self.frame_at(t)]

    def frame_period(self) -> float:
        return (self.t[-1] - self.t[-2]) if len(self.t) >= 2 else 0.1

    def gap_frames(self, k: int) -> float:
        return (self.t[k] - self.t[k - 1]) / self.nominal_period_s

    def level_frame(self) -> float | None:
        """A VO's frame is its first camera frame, often pitched a degree or two: projecting its
        motion on that frame's "horizontal" shortens distances by 1 − cos(tilt), which the scale
        then absorbs wrongly. Roads are level on average, so the mean of the body's up axis over
        the frames so far is up: rotate the frame so it is. Returns the angle (rad), or None when
        the mean up axis is too short to trust (the frame is left as it is)."""
        ups = np.array([p.rotation().matrix()[:, 2] for p in self.raw])
        up = ups.mean(axis=0)
        norm = np.linalg.norm(up)
        if norm < 0.5:
            return None
        up /= norm
        axis = np.cross(up, [0.0, 0.0, 1.0])
        angle = math.asin(min(1.0, float(np.linalg.norm(axis))))
        if angle < 1e-6:
            self.level_rot = gtsam.Pose3()
            return 0.0
        lvl = gtsam.Pose3(gtsam.Rot3.Rodrigues(axis / np.linalg.norm(axis) * angle), gtsam.Point3(0, 0, 0))
        self.level_rot = lvl
        self.raw = [lvl.compose(p) for p in self.raw]
        return angle

    def to_map(self, raw: gtsam.Pose3, a: Alignment) -> gtsam.Pose3:
        """A raw odometry pose in the map frame."""
        p = raw.translation() * a.scale
        c, s = math.cos(a.rot_rad), math.sin(a.rot_rad)
        xy = np.array([c * p[0] - s * p[1], s * p[0] + c * p[1]]) + a.trans_m
        rot = gtsam.Rot3.Yaw(a.rot_rad).compose(raw.rotation())
        pose = gtsam.Pose3(rot, gtsam.Point3(xy[0], xy[1], p[2]))
        return level(pose) if self.state is StateModel.planar else pose

    def step(self, k: int, scale: float) -> gtsam.Pose3:
        """The scaled relative motion into frame k in the engine's state model."""
        if self.state is StateModel.planar:
            rel = planar_step(self.raw[k - 1], self.raw[k])
        else:
            rel = self.rel[k]
        t = rel.translation() * scale
        return gtsam.Pose3(rel.rotation(), gtsam.Point3(*t))
