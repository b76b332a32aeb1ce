"""Running the engine on recorded data: reading odometry and GPS files, feeding :class:`MapFusion`
in time order, and collecting estimates. The engine itself knows no files; this module does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import numpy as np

from .config import FusionConfig, from_mapping
from .engine import MapFusion
from .errors import ConfigError
from .formats import (FormatError, GpsFixes, kitti_rows, kitti_to_matrices, read_times, read_toml, tum_rows,
                      tum_to_matrices)
from .roadmap import RoadMap


class OdometryFormat(str, Enum):
    tum = "tum"
    kitti = "kitti"


class OdometryFrame(str, Enum):
    body = "body"  # x forward, y left, z up
    camera = "camera"  # x right, y down, z forward


#: Camera axes expressed in the body frame: body x = camera z, body y = −camera x, body z = −camera y.
R_BODY_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_to_body(poses: np.ndarray) -> np.ndarray:
    """Absolute camera-frame poses (N, 4, 4) → body-frame poses of the same motion.

    T_body = C · T_cam · C⁻¹ with C the camera → body axis change: the first camera frame becomes
    a body frame (x forward, y left, z up) and every relative motion is re-expressed in it.
    """
    c = np.eye(4)
    c[:3, :3] = R_BODY_CAMERA
    return np.einsum("ij,njk,kl->nil", c, np.asarray(poses, dtype=float), c.T)


def body_to_camera(poses: np.ndarray) -> np.ndarray:
    """The inverse of :func:`camera_to_body`."""
    c = np.eye(4)
    c[:3, :3] = R_BODY_CAMERA
    return np.einsum("ij,njk,kl->nil", c.T, np.asarray(poses, dtype=float), c)


def read_odometry(path: str | Path, fmt: OdometryFormat = OdometryFormat.tum, times: str | Path | None = None,
                  frame: OdometryFrame = OdometryFrame.body) -> tuple[np.ndarray, np.ndarray]:
    """Odometry as (t (N,), absolute poses (N, 4, 4) in the body convention)."""
    parts = list(read_odometry_chunks(path, fmt, times, frame, chunk=1 << 62))
    if not parts:
        raise FormatError(f"{path}: no poses in the file")
    return parts[0]


def odometry_times(path: str | Path, fmt: OdometryFormat = OdometryFormat.tum,
                   times: str | Path | None = None) -> np.ndarray:
    """Every frame's time, the whole file read through and checked (nothing else kept): the first
    pass of a streamed fusion, which refuses a bad file before any work."""
    if OdometryFormat(fmt) is OdometryFormat.tum:
        t = np.fromiter((row[0] for row in tum_rows(path)), dtype=float)
    else:
        if times is None:
            raise FormatError("KITTI odometry needs --times (one timestamp a line)")
        t = read_times(times)
        n = sum(1 for _ in kitti_rows(path))
        if len(t) != n:
            raise FormatError(f"{path}: {n} poses but {times} has {len(t)} times")
    if not len(t):
        raise FormatError(f"{path}: no poses in the file")
    return t


def read_odometry_chunks(path: str | Path, fmt: OdometryFormat = OdometryFormat.tum, times: str | Path | None = None,
                         frame: OdometryFrame = OdometryFrame.body, chunk: int = 2048):
    """The odometry as (t, absolute poses (n, 4, 4), body convention) chunks of ``chunk`` frames,
    streamed (a long drive is never held whole; the numbers are those of :func:`read_odometry`)."""
    import itertools

    if OdometryFormat(fmt) is OdometryFormat.tum:
        rows = tum_rows(path)
        while block := list(itertools.islice(rows, chunk)):
            a = np.asarray(block, dtype=float)
            yield a[:, 0], _to_body(tum_to_matrices(a[:, 1:4], a[:, 4:8]), frame)
    else:
        if times is None:
            raise FormatError("KITTI odometry needs --times (one timestamp a line)")
        t_all = read_times(times)
        rows, start = kitti_rows(path), 0
        while block := list(itertools.islice(rows, chunk)):
            if start + len(block) > len(t_all):
                raise FormatError(f"{path}: more poses than {times} has times ({len(t_all)})")
            yield t_all[start:start + len(block)], _to_body(kitti_to_matrices(block), frame)
            start += len(block)
        if start != len(t_all):
            raise FormatError(f"{path}: {start} poses but {times} has {len(t_all)} times")


def _to_body(poses: np.ndarray, frame: OdometryFrame) -> np.ndarray:
    return camera_to_body(poses) if OdometryFrame(frame) is OdometryFrame.camera else poses


def load_fusion_config(path: str | Path | None, **overrides) -> FusionConfig:
    """A FusionConfig from a TOML file: its ``[mapfusion]`` table, or its top level."""
    data: dict = {}
    if path is not None:
        p = Path(path)
        raw = read_toml(p, "config file", ConfigError)
        data = raw.get("mapfusion", raw)
        where = str(p)
    else:
        where = "config"
    data = {**data, **overrides}
    return from_mapping(FusionConfig, data, where, prefix="mapfusion." if path else "")


@dataclass(frozen=True)
class MotionSamples:
    """Wheel speed and gyro yaw rate fed beside the odometry (issue 18): each in time order."""

    wheel_t_s: np.ndarray
    wheel_speed_mps: np.ndarray
    gyro_t_s: np.ndarray
    yaw_rate_radps: np.ndarray

    def merged(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t, is_wheel, value) of both streams in time order (a wheel sample first at equal times)."""
        t = np.concatenate((self.wheel_t_s, self.gyro_t_s))
        is_wheel = np.concatenate((np.ones(len(self.wheel_t_s), bool), np.zeros(len(self.gyro_t_s), bool)))
        v = np.concatenate((self.wheel_speed_mps, self.yaw_rate_radps))
        order = np.lexsort((~is_wheel, t))
        return t[order], is_wheel[order], v[order]


@dataclass
class FusionResult:
    t_s: np.ndarray
    online: list  # gtsam.Pose3 or None per frame
    smoothed: dict
    engine: MapFusion


def fuse(road: RoadMap, t_odo: np.ndarray, poses: np.ndarray, gps: GpsFixes | None, cfg: FusionConfig,
         progress=None, on_frame=None, motion: MotionSamples | None = None,
         start_region: tuple[float, float, float] | None = None) -> FusionResult:
    """Feed odometry (absolute poses in its own frame), GPS and (optionally) wheel speed and yaw rate to
    the engine in time order; ``on_frame(engine)`` after every frame. ``start_region`` (lat, lon, radius_m):
    a cold start without GPS (:meth:`MapFusion.start_in_region`)."""
    n = len(t_odo)
    if n < 2:
        raise FormatError("odometry: need at least two frames")
    eng = make_engine(road, t_odo, gps, cfg, start_region=start_region)
    feed(eng, [(np.asarray(t_odo), np.asarray(poses))], gps, n, progress, on_frame, motion)
    t_s, online = eng.online_estimates()
    return FusionResult(t_s, online, eng.trajectory(), eng)


def make_engine(road: RoadMap, t_odo: np.ndarray, gps: GpsFixes | None, cfg: FusionConfig, on_final=None,
                start_region: tuple[float, float, float] | None = None) -> MapFusion:
    """The engine for a recorded drive: its odometry and GPS rates from the median periods (and the cold
    start's region, (lat, lon, radius_m), when given)."""
    gps_rate = 1.0
    if gps is not None and len(gps) >= 2:
        gps_rate = 1.0 / float(np.median(np.diff(gps.t_s)))
    period = float(np.median(np.diff(t_odo)))
    eng = MapFusion(road, cfg, gps_rate_hz=gps_rate, odometry_rate_hz=1.0 / period, on_final=on_final)
    if start_region is not None:
        eng.start_in_region(*start_region)
    return eng


def fuse_streaming(road: RoadMap, path: str | Path, fmt: OdometryFormat, times: str | Path | None,
                   frame: OdometryFrame, gps: GpsFixes | None, cfg: FusionConfig, on_final, progress=None,
                   t_all: np.ndarray | None = None, motion: MotionSamples | None = None,
                   start_region: tuple[float, float, float] | None = None) -> MapFusion:
    """The engine over an odometry file of any length, in flat memory: the file is read through
    once to check it (and for its rate; ``t_all``: that pass's times, when the caller made it),
    then fed a chunk at a time; each frame goes to ``on_final(t, online, smoothed)`` once final
    (see :mod:`mapfusion.stream`). Returns the engine."""
    if t_all is None:
        t_all = odometry_times(path, fmt, times)
    if len(t_all) < 2:
        raise FormatError("odometry: need at least two frames")
    eng = make_engine(road, t_all, gps, cfg, on_final, start_region)
    n = len(t_all)
    del t_all
    feed(eng, read_odometry_chunks(path, fmt, times, frame), gps, n, progress, motion=motion)
    return eng


def feed(eng: MapFusion, chunks, gps: GpsFixes | None, n: int, progress=None, on_frame=None,
         motion: MotionSamples | None = None) -> None:
    """Feed (t, absolute poses) chunks, the fixes and the wheel and gyro samples to the engine in time
    order (at equal times: wheel and gyro, then GPS, then the frame), then finish it;
    ``on_frame(engine)`` after each frame the engine made (wheel + gyro make frames of their own where
    the odometry has none)."""
    gi, k = 0, 0
    ng = 0 if gps is None else len(gps)
    mt, mw, mv = motion.merged() if motion is not None else (np.empty(0), np.empty(0, bool), np.empty(0))
    mi, nm, seen = 0, len(mt), 0

    def samples_until(t_end: float) -> None:
        nonlocal mi, seen
        while mi < nm and mt[mi] <= t_end:
            (eng.add_wheel_speed if mw[mi] else eng.add_yaw_rate)(float(mt[mi]), float(mv[mi]))
            mi += 1
        while on_frame is not None and seen < eng.counters.frames:
            on_frame(eng)
            seen += 1

    prev = np.eye(4)
    for t_chunk, poses in chunks:
        inv = np.linalg.inv(poses[:-1])
        for j in range(len(t_chunk)):
            t = float(t_chunk[j])
            samples_until(t + 1e-9)
            while gps is not None and gi < ng and gps.t_s[gi] <= t + 1e-9:
                alt = gps.alt_m[gi]
                eng.add_gps(float(gps.t_s[gi]), float(gps.lat_deg[gi]), float(gps.lon_deg[gi]),
                            None if not math.isfinite(alt) else float(alt), float(gps.sigma_m[gi]))
                gi += 1
            if k == 0:
                rel = np.eye(4)
            elif j == 0:
                rel = np.linalg.inv(prev[None])[0] @ poses[0]
            else:
                rel = inv[j - 1] @ poses[j]
            eng.add_odometry(t, rel)
            samples_until(-math.inf)  # on_frame for the frame just made
            if progress is not None and k % 500 == 0:
                progress(k, n)
            k += 1
        prev = poses[-1]
    samples_until(math.inf)
    eng.finish()


def poses_to_arrays(poses: list) -> tuple[np.ndarray, np.ndarray]:
    """gtsam.Pose3 list → (xyz (N, 3), q_xyzw (N, 4))."""
    from .formats import matrices_to_tum

    return matrices_to_tum(np.array([p.matrix() for p in poses]))
