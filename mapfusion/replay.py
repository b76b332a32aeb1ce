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
from .formats import FormatError, GpsFixes, read_kitti_poses, read_times, read_toml, read_tum, tum_to_matrices
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
    if OdometryFormat(fmt) is OdometryFormat.tum:
        t, xyz, q = read_tum(path)
        poses = tum_to_matrices(xyz, q)
    else:
        if times is None:
            raise FormatError("KITTI odometry needs --times (one timestamp a line)")
        poses = read_kitti_poses(path)
        t = read_times(times)
        if len(t) != len(poses):
            raise FormatError(f"{path}: {len(poses)} poses but {times} has {len(t)} times")
    if OdometryFrame(frame) is OdometryFrame.camera:
        poses = camera_to_body(poses)
    return t, poses


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


@dataclass
class FusionResult:
    t_s: np.ndarray
    online: list  # gtsam.Pose3 or None per frame
    smoothed: dict
    engine: MapFusion


def fuse(road: RoadMap, t_odo: np.ndarray, poses: np.ndarray, gps: GpsFixes | None, cfg: FusionConfig,
         progress=None) -> FusionResult:
    """Feed odometry (absolute poses in its own frame) and GPS to the engine in time order."""
    n = len(t_odo)
    if n < 2:
        raise FormatError("odometry: need at least two frames")
    period = float(np.median(np.diff(t_odo)))
    gps_rate = 1.0
    if gps is not None and len(gps) >= 2:
        gps_rate = 1.0 / float(np.median(np.diff(gps.t_s)))
    eng = MapFusion(road, cfg, gps_rate_hz=gps_rate, odometry_rate_hz=1.0 / period)
    gi = 0
    ng = 0 if gps is None else len(gps)
    inv = np.linalg.inv(poses[:-1])
    for k in range(n):
        t = float(t_odo[k])
        while gps is not None and gi < ng and gps.t_s[gi] <= t + 1e-9:
            alt = gps.alt_m[gi]
            eng.add_gps(float(gps.t_s[gi]), float(gps.lat_deg[gi]), float(gps.lon_deg[gi]),
                        None if not math.isfinite(alt) else float(alt), float(gps.sigma_m[gi]))
            gi += 1
        rel = np.eye(4) if k == 0 else inv[k - 1] @ poses[k]
        eng.add_odometry(t, rel)
        if progress is not None and k % 500 == 0:
            progress(k, n)
    eng.finish()
    t_s, online = eng.online_estimates()
    return FusionResult(t_s, online, eng.trajectory(), eng)


def poses_to_arrays(poses: list) -> tuple[np.ndarray, np.ndarray]:
    """gtsam.Pose3 list → (xyz (N, 3), q_xyzw (N, 4))."""
    from .formats import matrices_to_tum

    return matrices_to_tum(np.array([p.matrix() for p in poses]))
