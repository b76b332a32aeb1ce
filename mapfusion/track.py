"""The odometry frames the engine has seen: times, raw poses in the odometry's own frame, the
relative motions, and each frame's causal estimate in the map frame.

Raw poses are the odometry as given (unscaled), composed from the relative motions; once the
planar state levels the odometry frame they are stored levelled. The engine's planar track
(:func:`track_for`) reduces each relative motion to a planar step (x, y, yaw) on the local horizontal
(:class:`LocalLevel`; ``flat`` alone takes it in the body frame, :func:`flatten`), so the raw chain is
level by construction and no tilt of the odometry's own frame reaches it. :class:`Alignment` (from the GPS
initialisation) takes a raw pose into the map frame.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

import gtsam
import numpy as np

from .config import FusionConfig, OutageStep, StateModel

log = logging.getLogger(__name__)

#: An odometry step implying more than this speed (scaled once initialised), and more than 20× the median of the
#: last 50 steps', is a VO failure (a corrupt pose, a relocalisation to a wrong place): counted (odometry_jumps),
#: logged and bridged with the last plausible motion, never followed. Unit: m/s. Source: issue 19: 70 m/s = 252
#: km/h, beyond any road vehicle; an impossible jump of 10,000 km was fused as motion.
MAX_ODOMETRY_SPEED_MPS = 70.0

#: The window over which the body's up axis is averaged into the local vertical. Unit: s.
#: Source: roads are level over a minute of driving.
LEVEL_WINDOW_S = 60.0

#: An odometry step spanning more than this is an outage: its σ is at least outage_step_fraction of its length and
#: OUTAGE_ROT_SIGMA_DEG. Unit: s. Source: a re-initialised VO guesses the motion it did not see.
OUTAGE_S = 1.0
T = TypeVar("T")


def level(p: gtsam.Pose3) -> gtsam.Pose3:
    """The pose with roll and pitch removed and z = 0 (a ground vehicle on the map plane)."""
    yaw = p.rotation().yaw()
    return gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(p.x(), p.y(), 0.0))


def planar_of(pose: gtsam.Pose3) -> tuple[float, float, float]:
    """(x, y, yaw) of a pose."""
    x, y, _ = pose.translation().tolist()
    return x, y, pose.rotation().yaw()


def flatten(rel: gtsam.Pose3) -> gtsam.Pose3:
    """A relative motion in the moving body's frame reduced to the ground plane: its x, y and yaw. Chained,
    such steps are immune to the odometry frame's own tilt (a VO that re-initialises after an outage may
    resume in a frame pitched by tens of degrees, and its horizontal displacements shrink by the cosine)."""
    t = rel.translation()
    return gtsam.Pose3(gtsam.Rot3.Yaw(rel.rotation().yaw()), gtsam.Point3(float(t[0]), float(t[1]), 0.0))


def _levelling_rows(ux: float, uy: float, uz: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """The first two rows of the rotation taking the direction (ux, uy, uz) to +z about their common
    perpendicular (Rodrigues; plain floats: this runs once a frame)."""
    n = math.sqrt(ux * ux + uy * uy + uz * uz)
    if not n > 1e-12:  # (up axes that cancel: an odometry flipping over; leave the frame as it is)
        return (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    ux, uy, uz = ux / n, uy / n, uz / n
    s2 = ux * ux + uy * uy  # |u × z|², the axis being (uy, -ux, 0)
    if s2 < 1e-24:
        return ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)) if uz > 0 else ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0))
    f = (1.0 - uz) / s2
    # I + K + K²·f with K the cross-product matrix of (uy, -ux, 0)
    return ((1.0 - f * ux * ux, -f * ux * uy, -ux), (-f * ux * uy, 1.0 - f * uy * uy, -uy))


class LocalLevel:
    """Odometry steps projected on the odometry frame's *local* horizontal: the plane normal to the mean of
    the body's up axis over the last ``window`` frames (roads are level on average). A frame that tilts —
    slowly, as a VO's attitude drifts, or at once, as a VO re-initialised after an outage resumes in a
    pitched frame (the window restarts after a gap over ``reset_after_s``) — is levelled again within the
    window, while a level frame is left as it is (the body's own roll and pitch on the road, and a camera
    mounted at a tilt, do not turn the heading as body-frame steps do)."""

    def __init__(self, window: int, reset_after_s: float) -> None:
        self.window, self.reset_after_s = max(1, int(window)), reset_after_s
        self._ups: deque[tuple[float, float, float]] = deque()
        self._sum = [0.0, 0.0, 0.0]
        self._pose: gtsam.Pose3 | None = None  # the 3-D chain of the relative motions
        self._fwd = (1.0, 0.0, 0.0)  # its last pose's forward axis and position, kept for the next step
        self._pos = (0.0, 0.0, 0.0)
        self._t = -math.inf

    def step(self, t: float, rel: gtsam.Pose3) -> gtsam.Pose3:
        """The planar step (x, y, yaw in the previous pose's levelled frame) into the frame at ``t``."""
        cur = self._pose.compose(rel) if self._pose is not None else gtsam.Pose3()
        if t - self._t > self.reset_after_s:
            self._ups.clear()
            self._sum = [0.0, 0.0, 0.0]
        (m00, _, m02, m03), (m10, _, m12, m13), (m20, _, m22, m23), _ = cur.matrix().tolist()  # (plain floats: fast)
        f0, p0 = self._fwd, self._pos
        f1, p1, up = (m00, m10, m20), (m03, m13, m23), (m02, m12, m22)
        self._pose, self._fwd, self._pos, self._t = cur, f1, p1, t
        self._ups.append(up)
        sm = self._sum
        sm[0] += up[0]
        sm[1] += up[1]
        sm[2] += up[2]
        if len(self._ups) > self.window:
            old = self._ups.popleft()
            sm[0] -= old[0]
            sm[1] -= old[1]
            sm[2] -= old[2]
        (a0, a1, a2), (b0, b1, b2) = _levelling_rows(sm[0], sm[1], sm[2])
        yaw0 = math.atan2(b0 * f0[0] + b1 * f0[1] + b2 * f0[2], a0 * f0[0] + a1 * f0[1] + a2 * f0[2])
        yaw1 = math.atan2(b0 * f1[0] + b1 * f1[1] + b2 * f1[2], a0 * f1[0] + a1 * f1[1] + a2 * f1[2])
        d0, d1, d2 = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
        return planar_step((0.0, 0.0, yaw0), (a0 * d0 + a1 * d1 + a2 * d2, b0 * d0 + b1 * d1 + b2 * d2, yaw1))


def planar_step(prev: tuple[float, float, float], cur: tuple[float, float, float], scale: float = 1.0) -> gtsam.Pose3:
    """Relative motion between two odometry poses given as (x, y, yaw) (:func:`planar_of`), projected on
    the horizontal plane with the odometry's own attitude: the world displacement rotated by the
    previous yaw only (dz, roll and pitch dropped), the translation times ``scale``."""
    x0, y0, yaw0 = prev
    x1, y1, yaw1 = cur
    dx, dy = x1 - x0, y1 - y0
    c, s = math.cos(yaw0), math.sin(yaw0)
    t = gtsam.Point3((c * dx + s * dy) * scale, (-s * dx + c * dy) * scale, 0.0)
    return gtsam.Pose3(gtsam.Rot3.Yaw(yaw1 - yaw0), t)


def spread_back(path: list[gtsam.Pose3], was: gtsam.Pose3, now: gtsam.Pose3) -> list[gtsam.Pose3]:
    """The compass rule of traverse adjustment: ``path`` runs from a pose known to be right (its first) to
    just before a pose that a correction moved from ``was`` to ``now``; each pose after the first is moved by
    that correction's position and heading change times the fraction of the path's length driven to it (a
    drift that grows with the distance driven is undone; the first pose stays). Returns those poses."""
    xy = np.array([[p.x(), p.y()] for p in path] + [[was.x(), was.y()]])
    driven = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))))
    if driven[-1] <= 0.0:
        return list(path[1:])
    dx, dy = now.x() - was.x(), now.y() - was.y()
    dyaw = math.remainder(now.rotation().yaw() - was.rotation().yaw(), 2.0 * math.pi)
    return [gtsam.Pose3(gtsam.Rot3.Yaw(f * dyaw).compose(p.rotation()), gtsam.Point3(p.x() + f * dx, p.y() + f * dy,
                                                                                       p.z()))
            for p, f in zip(path[1:], (driven[1:-1] / driven[-1]).tolist())]


@dataclass(frozen=True)
class Alignment:
    """The odometry frame in the map frame: scale, then a rotation by ``rot_rad`` about z, then a
    shift by ``trans_m`` (x, y)."""

    scale: float
    scale_sigma: float
    rot_rad: float
    trans_m: np.ndarray

    @property
    def relative_sigma(self) -> float:
        """The scale's σ over the scale: what it makes of a step's length in metres (a mono VO's scale is ~30)."""
        return self.scale_sigma / self.scale


class History(Generic[T]):
    """A list indexed by absolute frame number whose oldest items can be dropped, so a drive of any
    length holds a bounded history. Negative indices count from the end, as in a list; a dropped
    frame raises IndexError (never a wrong frame)."""

    def __init__(self) -> None:
        self._items: list[T] = []
        self.first = 0  # the oldest frame still held

    def __len__(self) -> int:
        return self.first + len(self._items)

    def _at(self, k: int) -> int:
        # negative indices count from the end, which the held list shares; it raises past its start
        i = k if k < 0 else k - self.first
        if i < 0 <= k:
            raise IndexError(f"frame {k} is not held (frames {self.first}..{len(self) - 1})")
        return i

    def __getitem__(self, k: int) -> T:  # on the engine's per-frame path: kept to two comparisons
        i = k if k < 0 else k - self.first
        if i < 0 <= k:
            raise IndexError(f"frame {k} is not held (frames {self.first}..{len(self) - 1})")
        return self._items[i]

    def __setitem__(self, k: int, value: T) -> None:
        self._items[self._at(k)] = value

    def __iter__(self) -> Iterator[T]:
        if self.first:
            raise IndexError(f"frames before {self.first} were dropped: iterate over held() instead")
        return iter(self._items)

    def held(self) -> Iterator[tuple[int, T]]:
        """(frame, item) of every frame still held."""
        return enumerate(self._items, start=self.first)

    def append(self, value: T) -> None:
        self._items.append(value)

    def drop_before(self, k: int) -> None:
        """Forget frames before k."""
        n = min(k, len(self)) - self.first
        if n > 0:
            del self._items[:n]
            self.first += n


class Track:
    """Odometry frames in time order, and their causal estimates (None before initialisation)."""

    def __init__(self, state: StateModel, nominal_period_s: float, flat: bool = False,
                 level: LocalLevel | None = None, nonholonomic: bool = False, slip_rad: float = 0.0) -> None:
        self.state = state
        self.nonholonomic = nonholonomic
        self.slip_rad = slip_rad
        self.lever_arm = LeverArm()
        # planar state, steps taken in the body frame (flat) or on the local horizontal (level): the raw chain
        # is composed of each step's x, y and yaw
        self.level = level if state is StateModel.planar else None
        self.flat = (flat or self.level is not None) and state is StateModel.planar
        self.nominal_period_s = nominal_period_s
        self.t: History[float] = History()
        self.raw: History[gtsam.Pose3] = History()  # raw absolute odometry poses (levelled once level is set)
        self.rel: History[gtsam.Pose3] = History()  # raw relative motion into each frame (identity for the first)
        self.online: History[gtsam.Pose3 | None] = History()
        # each frame's step as plain floats, for _sliding's look back over the last frames (None without
        # odometry_nonholonomic)
        self._slides: History[StepFloats | None] = History()
        self.level_rot: gtsam.Pose3 | None = None
        self._odo_abs = gtsam.Pose3()
        self._planar_memo: tuple[gtsam.Pose3, tuple[float, float, float]] | None = None

    def __len__(self) -> int:
        return len(self.t)

    def append(self, t: float, rel: gtsam.Pose3) -> np.ndarray:
        """A new frame from its relative motion; returns its raw (unlevelled) position."""
        first = not self.t
        if self.level is not None:
            rel = self.level.step(t, rel)
        elif self.flat:
            rel = flatten(rel)
        self._odo_abs = self._odo_abs if first else self._odo_abs.compose(rel)
        short = self.nonholonomic and not first and t - self.t[-1] <= NONHOLONOMIC_MAX_S
        if short:
            self.lever_arm.add(rel)
        self.t.append(t)
        self.raw.append(self.level_rot.compose(self._odo_abs) if self.level_rot is not None else self._odo_abs)
        self.rel.append(gtsam.Pose3() if first else rel)
        self._slides.append(_step_floats(self.rel[-1], short) if self.nonholonomic else None)
        self.online.append(None)
        return self._odo_abs.translation()

    def restate_steps(self, steps: dict[int, gtsam.Pose3]) -> list[np.ndarray] | None:
        """Replace the relative motions of some frames and recompose every raw pose after the first of
        them; returns every held frame's raw (unlevelled) position, or None when nothing changed."""
        if not steps:
            return None
        k0 = min(steps)
        for k, rel in steps.items():
            self.rel[k] = flatten(rel) if self.flat else rel
            if self.nonholonomic:
                self._slides[k] = _step_floats(self.rel[k], k > self.first and self.t[k] - self.t[k - 1] <=
                                               NONHOLONOMIC_MAX_S)
        for k in range(max(k0, self.first + 1), len(self)):
            self.raw[k] = self.raw[k - 1].compose(self.rel[k])
        unlevel = self.level_rot.inverse() if self.level_rot is not None else gtsam.Pose3()
        self._odo_abs = unlevel.compose(self.raw[len(self) - 1])
        return [unlevel.compose(p).translation() for _, p in self.raw.held()]

    @property
    def first(self) -> int:
        """The oldest frame still held (0 unless :meth:`drop_before` was called)."""
        return self.t.first

    def drop_before(self, k: int) -> None:
        """Forget the frames before k (their times, poses and estimates)."""
        for h in (self.t, self.raw, self.rel, self.online, self._slides):
            h.drop_before(k)

    def frame_at(self, t: float) -> int:
        """Index of the nearest held frame in time (bisect: the frame list only grows)."""
        i = min(bisect.bisect_left(self.t, t, lo=self.first), len(self.t) - 1)
        if i > self.first and abs(self.t[i - 1] - t) <= abs(self.t[i] - t):
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
        for k, p in list(self.raw.held()):
            self.raw[k] = lvl.compose(p)
        return angle

    def to_map(self, raw: gtsam.Pose3, a: Alignment) -> gtsam.Pose3:
        """A raw odometry pose in the map frame."""
        p = raw.translation() * a.scale
        c, s = math.cos(a.rot_rad), math.sin(a.rot_rad)
        xy = np.array([c * p[0] - s * p[1], s * p[0] + c * p[1]]) + a.trans_m
        rot = gtsam.Rot3.Yaw(a.rot_rad).compose(raw.rotation())
        pose = gtsam.Pose3(rot, gtsam.Point3(xy[0], xy[1], p[2]))
        return level(pose) if self.state is StateModel.planar else pose

    def _planar(self, pose: gtsam.Pose3) -> tuple[float, float, float]:
        """:func:`planar_of` of a raw pose; the last one read is kept, as the next frame's step starts
        from it (by identity: a restated or levelled pose is a new object)."""
        memo = self._planar_memo
        if memo is not None and memo[0] is pose:
            return memo[1]
        got = planar_of(pose)
        self._planar_memo = (pose, got)
        return got

    def step(self, k: int, scale: float) -> gtsam.Pose3:
        """The scaled relative motion into frame k in the engine's state model."""
        if self.state is StateModel.planar:
            step = planar_step(self._planar(self.raw[k - 1]), self._planar(self.raw[k]), scale)
        else:
            rel = self.rel[k]
            step = gtsam.Pose3(rel.rotation(), gtsam.Point3(*(rel.translation() * scale)))
        if self.nonholonomic and self.t[k] - self.t[k - 1] <= NONHOLONOMIC_MAX_S and self._sliding(k, scale):
            return along_heading(step, self.lever_arm.lever(scale))
        return step

    def _sliding(self, k: int, scale: float) -> bool:
        """The odometry's frames up to k slid sideways, over the last SLIDE_FRAMES (at least SLIDE_MIN_M of driving
        at the odometry's ``scale``), by more than ``slip_rad`` (always, with ``slip_rad`` 0)."""
        if self.slip_rad <= 0.0:
            return True
        lever = self.lever_arm.lever(1.0)
        across = along = turn = 0.0
        slides = self._slides
        held = slides.first
        lo = max(self.first + 1, k - SLIDE_FRAMES + 1)
        slides[k]  # (a frame that is not held raises IndexError, as reading it does)
        # (the held list's own slice and _slide's arithmetic written out: this runs every frame, issue 21)
        for f in slides._items[max(lo - held, 0):k + 1 - held]:
            if f is not None and f[7]:  # (held for every frame when nonholonomic; f[7]: a short step)
                x, y, absyaw, cos_m1, sin_yaw, c, s, _ = f
                ax, ay = x - lever * cos_m1, y - lever * sin_yaw
                b, a = c * ax + s * ay, -s * ax + c * ay
                if not b >= 0.0:  # (as _slide: a backward step's taken the other way round)
                    a, b = -a, -b
                across, along, turn = across + a, along + b, turn + absyaw
        return along * scale >= SLIDE_MIN_M and turn <= SLIDE_MAX_TURN_RAD and \
            abs(across) > math.tan(self.slip_rad) * along


#: odometry_nonholonomic turns steps over at most this long: a second of driving is near enough an arc, whose chord
#: points along the mean of its end headings; a step across a longer gap is a re-initialised odometry's guess.
NONHOLONOMIC_MAX_S = 1.0


def along_heading(step: gtsam.Pose3, lever_m: float = 0.0) -> gtsam.Pose3:
    """The step with its horizontal displacement turned onto the direction a wheeled vehicle moves in
    (``odometry_nonholonomic``). The point of the vehicle that does not slide (the rear axle's middle) lies
    ``lever_m`` behind the odometry's frame: its step, the measured one less the lever's swing, is turned
    along the mean of the step's start and end headings (the chord of an arc), forwards or backwards as it
    went, its length kept; the lever's swing is added back. z and the rotation are kept."""
    x, y, z = step.translation()
    yaw = step.rotation().yaw()
    sx, sy = _swing(yaw, lever_m)
    ax, ay = x - sx, y - sy
    d = math.hypot(ax, ay)
    if d == 0.0:
        return step
    half = 0.5 * yaw
    d = d if ax >= 0.0 else -d
    return gtsam.Pose3(step.rotation(), gtsam.Point3(d * math.cos(half) + sx, d * math.sin(half) + sy, z))


def _swing(yaw_rad: float, lever_m: float) -> tuple[float, float]:
    """How far a frame ``lever_m`` ahead of the rear axle moves beyond the axle's own motion in a turn of
    ``yaw_rad``, in the step's start frame (x, y)."""
    return lever_m * (math.cos(yaw_rad) - 1.0), lever_m * math.sin(yaw_rad)


def slide_of(step: gtsam.Pose3, lever_m: float = 0.0) -> tuple[float, float]:
    """The step's motion beyond the lever's swing, across and along its mean heading: (sideways, along) (its own
    units; along is ≥ 0, a backward step's taken the other way round)."""
    return _slide(_step_floats(step, False), lever_m)


#: A step as plain floats: x, y, |yaw|, cos(yaw) − 1, sin(yaw), cos(yaw / 2), sin(yaw / 2), and whether it follows its
#: previous frame within NONHOLONOMIC_MAX_S (what :func:`_slide` needs whatever the lever).
StepFloats = tuple[float, float, float, float, float, float, float, bool]


def _step_floats(step: gtsam.Pose3, short: bool) -> StepFloats:
    """A step's :data:`StepFloats` (the engine reads each frame's once, when it is appended)."""
    x, y, _ = step.translation().tolist()
    yaw = step.rotation().yaw()
    return x, y, abs(yaw), math.cos(yaw) - 1.0, math.sin(yaw), math.cos(0.5 * yaw), math.sin(0.5 * yaw), short


def _slide(f: StepFloats, lever_m: float) -> tuple[float, float]:
    """:func:`slide_of` of a step given as :data:`StepFloats` (:func:`_swing`'s arithmetic, its cosines read)."""
    x, y, _, cos_m1, sin_yaw, c, s, _ = f
    ax, ay = x - lever_m * cos_m1, y - lever_m * sin_yaw
    along, across = c * ax + s * ay, -s * ax + c * ay
    return (across, along) if along >= 0.0 else (-across, -along)


#: A slide is told over this many frames (a second at 10 Hz): a good odometry's steps scatter about their heading by a
#: degree or so, a VO's slide in rain holds its direction for seconds.
SLIDE_FRAMES = 10
#: ... and over at least this much driving (m): at a crawl a step's direction is its noise. KITTI 00's own poses move
#: 10 degrees across their heading for a second at 2.4 m/s in a slow turn (233 s); at 2 m the steps along the heading
#: took them 0.454 -> 0.489 m ATE with the map.
SLIDE_MIN_M = 3.0
#: ... turning at most this much (rad): in a sharp turn the frame's swing (a lever arm a few decimetres off) and the
#: tyres' own slip are degrees.
SLIDE_MAX_TURN_RAD = 0.1

#: The lever arm is estimated once the steps' turns add up to this (Σ sin² of each step's turn, rad²: a 90°
#: turn at 10 Hz and 10 m/s gives ~0.1), and it is held within LEVER_MAX_M of the frame.
LEVER_MIN_TURN = 0.05
LEVER_MAX_M = 5.0


class LeverArm:
    """How far ahead of the rear axle the odometry's frame lies, from its own steps: in a turn that frame
    swings sideways by lever × sin(turn) beyond the axle's arc (a camera 1.5 m ahead of it, 2.4 m across a
    right-angle turn), which :func:`along_heading` must keep. A least-squares fit over the run of each step's
    sideways motion beyond the arc's on sin(turn); a VO's slides (rain) do not follow the turns, and only
    widen the fit. In the odometry's own units."""

    def __init__(self) -> None:
        self._sxy = self._sxx = 0.0

    def add(self, step: gtsam.Pose3) -> None:
        x, y, _ = step.translation()
        yaw = step.rotation().yaw()
        d = math.hypot(x, y)
        s = math.sin(yaw)
        self._sxy += (y - math.copysign(d, x) * math.sin(0.5 * yaw)) * s
        self._sxx += s * s

    def lever(self, scale: float) -> float:
        """The lever arm in metres at the odometry's ``scale`` (0 until the turns suffice)."""
        if self._sxx < LEVER_MIN_TURN:
            return 0.0
        return min(max(self._sxy / self._sxx * scale, -LEVER_MAX_M), LEVER_MAX_M)


def track_for(cfg: FusionConfig, odometry_rate_hz: float) -> Track:
    """The engine's track for a configuration: its state model and how planar steps are taken."""
    level = LocalLevel(round(LEVEL_WINDOW_S * odometry_rate_hz), OUTAGE_S)
    return Track(cfg.state, 1.0 / odometry_rate_hz, level=level,
                 nonholonomic=cfg.odometry_nonholonomic, slip_rad=math.radians(cfg.odometry_slip_deg))


class JumpGuard:
    """Odometry steps implying an impossible speed (a VO failure: a corrupt pose, a relocalisation to
    a wrong place) are flagged and bridged with the last plausible motion (constant velocity).

    A step is impossible when its speed exceeds ``max_speed_mps`` (scaled by the odometry's scale
    once known) and 20 times the median of the last 50 plausible steps (so a monocular odometry of
    unknown scale is not flagged for its units alone). A step over a gap longer than ``gap_s`` (the VO
    lost track; where it says it resumed is its own guess) is replaced by the last plausible velocity,
    straight on over the gap (``gap_bridged``; not a jump).
    """

    RATIO, HISTORY, MIN_HISTORY, MIN_TYPICAL_MPS = 20.0, 50, 10, 0.5

    def __init__(self, max_speed_mps: float, gap_s: float = math.inf) -> None:
        self.max_speed_mps = max_speed_mps
        self.gap_s = gap_s  # a step over a longer gap is replaced by the last velocity, straight on
        self.gap_bridged = False  # the last step checked was such a gap
        self.gap_yaw_rad = 0.0  # and the odometry's own turn over it (the only word on a turn in the gap)
        self._speeds: deque[float] = deque(maxlen=self.HISTORY)
        self._last: tuple[float, gtsam.Pose3] | None = None  # (dt, rel) of the last plausible step
        self._t: float | None = None

    @classmethod
    def for_config(cls, cfg: FusionConfig) -> JumpGuard:
        """The engine's guard: gaps bridged by the last velocity unless ``outage_step`` is the odometry's own."""
        return cls(MAX_ODOMETRY_SPEED_MPS, math.inf if cfg.outage_step is OutageStep.odometry else cfg.reloc_gap_s)

    def check(self, t: float, rel: gtsam.Pose3, scale: float | None) -> tuple[gtsam.Pose3, bool]:
        """The step to use into the frame at ``t``, and whether ``rel`` was an impossible jump."""
        if self._t is None:
            self._t = t
            return rel, False
        dt, self._t = max(t - self._t, 1e-3), t
        self.gap_bridged = dt > self.gap_s and self._last is not None
        if self.gap_bridged:
            self.gap_yaw_rad = rel.rotation().yaw()
            return self._carried(dt, gtsam.Rot3()), False
        tr = rel.translation()
        speed = math.sqrt(tr.dot(tr)) * (scale or 1.0) / dt  # (np.linalg.norm's own arithmetic, less its overhead)
        impossible = False
        if speed > self.max_speed_mps:  # rare: only then the median of the odometry's own speeds is needed
            seen = len(self._speeds) >= self.MIN_HISTORY
            typical = float(np.median(self._speeds)) if seen else math.inf
            impossible = speed > self.RATIO * max(typical, self.MIN_TYPICAL_MPS)
        if impossible and self._last is not None:
            return self._carried(dt, self._last[1].rotation()), True
        self._speeds.append(speed)
        self._last = (dt, rel)
        return rel, False

    def _carried(self, dt: float, rotation: gtsam.Rot3) -> gtsam.Pose3:
        """The last plausible step's velocity carried over ``dt``, with ``rotation``."""
        assert self._last is not None
        last_dt, last = self._last
        return gtsam.Pose3(rotation, gtsam.Point3(*(last.translation() * (dt / last_dt))))

    def bridge(self, t: float, rel: gtsam.Pose3, scale: float | None, counters) -> gtsam.Pose3:
        """:meth:`check`, counting (``counters.odometry_jumps``) and logging a bridged jump."""
        step, jump = self.check(t, rel, scale)
        if self.gap_bridged:
            log.info("the odometry resumed at t = %.3f s after a gap: the last velocity carried straight over it", t)
        if jump:
            counters.odometry_jumps += 1
            log.warning("the odometry step into t = %.3f s implies an impossible speed: bridged", t)
        return step
