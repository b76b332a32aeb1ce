"""Recorded drives in place of SUMO: a KITTI sequence or a TUM truth, with their own GPS.

A scenario's ``truth`` names the drive (DESIGN "Scenario files"). The sensor models then read
this truth instead of a simulated one; with ``[gps] source = "recorded"`` the engine gets the
drive's own fixes (KITTI: the RTK track moved to camera 0 by the fitted lever arm), selected by
the scenario's GPS mode, rate and interval.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapfusion.errors import InputError
from mapfusion.formats import quaternion_to_yaw, read_gps_csv, read_tum
from mapfusion.roadmap import RoadMap

from .scenario import GpsConfig, Scenario
from .sensors import GpsOutput, Truth, gps_fix_times, under_bridges

log = logging.getLogger(__name__)


@dataclass
class RecordedDrive:
    """A recorded truth in the map's ENU frame and the drive's own GPS fixes (ENU, may be empty)."""

    truth: Truth
    z_m: np.ndarray
    gps_t_s: np.ndarray
    gps_xyz_m: np.ndarray  # (K, 3) ENU, z relative to the map origin's altitude as the truth's
    source: str
    georef_residual_m: float | None = None

    @property
    def length_m(self) -> float:
        return float(np.sum(np.hypot(np.diff(self.truth.x_m), np.diff(self.truth.y_m))))


def recorded_truth(t_s: np.ndarray, xyz: np.ndarray, yaw_rad: np.ndarray, sc: Scenario, road: RoadMap,
                   where: str, imu_missing: np.ndarray | None = None) -> Truth:
    """A :class:`Truth` for the sensor models from recorded poses in the map's ENU frame.

    GPS-denied, visually degraded stretches are the scenario's ``[[tunnels]]`` zones by distance
    along the path, plus frames under a bridge of the map (nothing tells which road a recorded
    drive was on, so OSM tunnels are not known). ``imu_missing``: frames without inertial measurements
    (a KITTI drive's GPS/INS track filled by interpolation). Raises InputError when the truth lies off the map.
    """
    road.check_covers(xyz[:, :2], f"{where}: the truth on the map {sc.map} (is it in that map's ENU frame, "
                      "as mapfusion import kitti writes it for the same map?)")
    dist = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xyz[:, :2], axis=0).T))))
    zone = np.zeros(len(t_s), dtype=bool)
    for z in sc.tunnels:
        zone |= (dist >= z.start_m) & (dist <= z.end_m)
    bridge = under_bridges(road, xyz[:, 0], xyz[:, 1], np.full(len(t_s), -1), sc.gps.bridge_lane_width_m)
    denied = (zone if sc.gps.deny_in_tunnels else np.zeros_like(zone)) | (bridge if sc.gps.deny_under_bridges else False)
    return Truth(np.asarray(t_s, float), xyz[:, 0].copy(), xyz[:, 1].copy(), xyz[:, 2].copy(),
                 np.asarray(yaw_rad, float), denied, zone, imu_missing)


def _check_frame(path: Path, sc: Scenario) -> None:
    info = path.parent / "import.json"
    if info.exists():  # mapfusion import kitti records the map whose frame the truth is in
        recorded = json.loads(info.read_text()).get("map")
        if recorded and Path(recorded).resolve() != Path(sc.map).resolve():
            raise InputError(f"{path}: this truth is in the ENU frame of {recorded}, not of the scenario's map {sc.map}")


def load_recorded(path: str | Path, sc: Scenario, road: RoadMap) -> RecordedDrive:
    """The recorded drive at ``path`` (a KITTI sequence directory or a TUM file) in ``road``'s frame,
    cut to the scenario's ``duration_s``."""
    p = Path(path)
    if p.is_dir():
        from mapfusion.kitti import import_kitti, track_at_camera
        from scipy.spatial.transform import Rotation

        imp = import_kitti(p / "poses.txt", p / "times.txt", p / "rtk_gps.kml", road.projection)
        xyz = imp.truth_enu[:, :3, 3]
        yaw = Rotation.from_matrix(imp.truth_enu[:, :3, :3]).as_euler("ZYX")[:, 0]
        t = imp.t_s
        gps_t, gps_xyz = t.copy(), track_at_camera(imp, road.projection)
        residual = imp.georef.residual_rmse_m
        missing = imp.filled  # the GPS/INS unit's gaps: no inertial measurement there either
        log.info("%s: georeferenced to its RTK track, residual %.3f m RMSE", p, residual)
    else:
        _check_frame(p, sc)
        t, xyz, q = read_tum(p)
        yaw = quaternion_to_yaw(q)
        gps_path = p.parent / "gps.csv"
        if gps_path.exists():
            fixes = read_gps_csv(gps_path)
            gx, gy = road.projection.to_enu(fixes.lat_deg, fixes.lon_deg)
            gz = np.nan_to_num(np.asarray(fixes.alt_m, float))
            gps_t, gps_xyz = np.asarray(fixes.t_s, float), np.column_stack([gx, gy, gz])
        else:
            gps_t, gps_xyz = np.zeros(0), np.zeros((0, 3))
        residual = None
        missing = None
    keep = t - t[0] <= sc.duration_s + 1e-9
    truth = recorded_truth(t[keep], xyz[keep], yaw[keep], sc, road, str(p), None if missing is None else missing[keep])
    gkeep = gps_t - t[0] <= sc.duration_s + 1e-9
    return RecordedDrive(truth, xyz[keep, 2].copy(), gps_t[gkeep], gps_xyz[gkeep], str(p), residual)


def recorded_gps(rec: RecordedDrive, cfg: GpsConfig) -> GpsOutput:
    """The drive's own fixes at the times the GPS mode selects, none where the truth is GPS-denied
    (``[[tunnels]]`` zones, under bridges), declared with ``sigma_m``."""
    if len(rec.gps_t_s) == 0:
        raise InputError(f"{rec.source}: gps.source = \"recorded\" but the recorded drive has no GPS "
                         "(a TUM truth needs a gps.csv beside it)")
    t0 = float(rec.truth.t_s[0])
    idx = gps_fix_times(rec.gps_t_s - t0, cfg)
    # a fix is denied where the nearest truth frame is
    tf = np.searchsorted(rec.truth.t_s, rec.gps_t_s[idx]).clip(0, len(rec.truth) - 1)
    ok = ~rec.truth.gps_denied[tf]
    idx, tf = idx[ok], tf[ok]
    k = len(idx)
    g = rec.gps_xyz_m[idx]
    return GpsOutput(rec.gps_t_s[idx], g[:, 0].copy(), g[:, 1].copy(), g[:, 2].copy(), np.full(k, cfg.sigma_m),
                     np.zeros(k, dtype=bool), tf)
