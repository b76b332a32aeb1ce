"""KITTI odometry sequences in the project's formats (``mapfusion import kitti``).

The camera-0 poses (KITTI ground truth, in camera 0's frame at frame 0) are georeferenced by
fitting them to the RTK GPS track: p_gps,k = R · (t_k + R_k · ℓ) + t, with R, t the rigid motion
into the map's ENU frame and ℓ the antenna's lever arm in the camera frame. The fit alternates a
Umeyama alignment for R with a linear least-squares solve for t and ℓ; its residual is reported.
The truth is the camera's pose in ENU with body axes (x forward, y left, z up). Track points the
recording filled by interpolation (exactly straight, evenly spaced runs) are left out of the fit
and of its residual.

The track covers the raw recording, one point a raw frame; an odometry sequence may begin later in it
(KITTI 08 begins at raw frame 1,100). The offset is found by the step lengths: the sequence's
frame-to-frame distances slid along the track's, the offsets whose squared differences sum least
georeferenced in turn, and the one whose fit leaves the least residual kept (:func:`track_offsets`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .formats import FormatError, read_text, write_gps_csv, write_tum
from .metrics import umeyama
from .projection import LocalProjection
from .replay import R_BODY_CAMERA


def read_kml_track(path: str | Path) -> np.ndarray:
    """The first LineString of a KML file as (N, 3) lon, lat, alt.

    Read with an XML parser (expat) that refuses any DOCTYPE: KML needs no DTD, and a DTD is where
    entity bombs and external entities live. Malformed XML is a :class:`FormatError` with its line.
    """
    from xml.parsers import expat

    p = Path(path)
    data = read_text(p, "KML file").encode("utf-8")
    parser = expat.ParserCreate(namespace_separator=" ")
    stack: list[str] = []
    found: dict = {}  # "text": the first LineString's coordinates, "line": where they start

    def refuse(*_args) -> None:
        raise FormatError(f"{p}:{parser.CurrentLineNumber}: a DOCTYPE or entity declaration (KML needs none)")

    def start(name: str, _attrs) -> None:
        stack.append(name.rsplit(" ", 1)[-1])
        if stack[-1] == "coordinates" and "LineString" in stack and "text" not in found:
            found["parts"], found["line"] = [], parser.CurrentLineNumber

    def end(_name: str) -> None:
        if stack.pop() == "coordinates" and "parts" in found and "text" not in found:
            found["text"] = "".join(found.pop("parts"))

    def chars(text: str) -> None:
        if "parts" in found and stack and stack[-1] == "coordinates":
            found["parts"].append(text)

    parser.StartDoctypeDeclHandler = refuse
    parser.EntityDeclHandler = refuse
    parser.StartElementHandler, parser.EndElementHandler, parser.CharacterDataHandler = start, end, chars
    try:
        parser.Parse(data, True)
    except expat.ExpatError as exc:
        raise FormatError(f"{p}:{exc.lineno}: not well-formed XML ({expat.ErrorString(exc.code)})") from None
    if "text" not in found:
        raise FormatError(f"{p}: no LineString with coordinates in the KML")
    start_line = found["line"]
    rows = []
    for i, tok in enumerate(found["text"].split()):
        parts = tok.split(",")
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise FormatError(f"{p}:{start_line}: coordinate {i + 1} is not lon,lat[,alt]: {tok[:40]!r}") from None
        if len(vals) not in (2, 3) or not np.all(np.isfinite(vals)) or abs(vals[0]) > 180 or abs(vals[1]) > 90:
            raise FormatError(f"{p}:{start_line}: coordinate {i + 1} is not lon,lat[,alt]: {tok[:40]!r}")
        rows.append(vals if len(vals) == 3 else vals + [0.0])
    if len(rows) < 3:
        raise FormatError(f"{p}: the LineString has fewer than 3 points")
    return np.asarray(rows)


@dataclass(frozen=True)
class Georeference:
    """ENU ← camera-world rigid motion, the antenna lever arm, and the fit's residual."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    lever_arm_cam_m: np.ndarray  # (3,) antenna in the camera frame (x right, y down, z forward)
    residual_rmse_m: float
    residual_rmse_xy_m: float
    residuals_m: np.ndarray  # (N,) per frame
    scale: float = 1.0  # KITTI's poses come from a Mercator projection exact at the start latitude only

    def camera_to_enu(self, poses_cam: np.ndarray) -> np.ndarray:
        """Camera poses (N, 4, 4) → poses in ENU with body axes (x forward, y left, z up)."""
        out = np.tile(np.eye(4), (len(poses_cam), 1, 1))
        out[:, :3, :3] = np.einsum("ij,njk,kl->nil", self.rotation, poses_cam[:, :3, :3], R_BODY_CAMERA.T)
        out[:, :3, 3] = self.scale * poses_cam[:, :3, 3] @ self.rotation.T + self.translation
        return out


def filled_points(track_lonlatalt: np.ndarray, min_run: int = 3) -> np.ndarray:
    """Points of the track inside runs that are exactly straight and evenly spaced: gaps the
    recording filled by interpolation (shared/data/README.md), not measurements."""
    ll = track_lonlatalt[:, :2]
    second = np.abs(ll[2:] - 2 * ll[1:-1] + ll[:-2]).max(axis=1)
    flat = np.concatenate(([False], second < 1e-11, [False]))
    out = np.zeros(len(ll), dtype=bool)
    i = 0
    while i < len(flat):
        if flat[i]:
            j = i
            while j < len(flat) and flat[j]:
                j += 1
            if j - i >= min_run:
                out[i - 1:j + 1] = True  # the run's ends are interpolated too
            i = j
        else:
            i += 1
    return out


def georeference(poses_cam: np.ndarray, gps_enu: np.ndarray, iterations: int = 10,
                 use: np.ndarray | None = None, fit_scale: bool = True) -> Georeference:
    """Fit R, t and the lever arm ℓ so that R · (t_k + R_k ℓ) + t matches the GPS (both (N, ...)),
    on the points in ``use`` (default all); residuals are reported over the same points."""
    n = len(poses_cam)
    if len(gps_enu) != n:
        raise ValueError("georeference: one GPS position per pose")
    use = np.ones(n, dtype=bool) if use is None else np.asarray(use, dtype=bool)
    poses_cam, gps_enu, n = poses_cam[use], gps_enu[use], int(use.sum())
    t_cam = poses_cam[:, :3, 3]
    r_cam = poses_cam[:, :3, :3]
    lever: np.ndarray = np.zeros(3)
    trans: np.ndarray = np.zeros(3)
    rot = np.eye(3)
    scale = 1.0
    for _ in range(iterations):
        src = t_cam + np.einsum("nij,j->ni", r_cam, lever)
        rot, _, scale = umeyama(src, gps_enu, with_scale=fit_scale)
        # G_k − s R t_k = t + s R R_k ℓ: linear in (t, ℓ)
        a = np.zeros((3 * n, 6))
        a[:, :3] = np.tile(np.eye(3), (n, 1))
        a[:, 3:] = scale * np.einsum("ij,njk->nik", rot, r_cam).reshape(3 * n, 3)
        rhs = (gps_enu - scale * t_cam @ rot.T).reshape(3 * n)
        sol, *_ = np.linalg.lstsq(a, rhs, rcond=None)
        trans, lever = sol[:3], sol[3:]
    pred = scale * (t_cam + np.einsum("nij,j->ni", r_cam, lever)) @ rot.T + trans
    res = gps_enu - pred
    per = np.linalg.norm(res, axis=1)
    return Georeference(rot, trans, lever, float(np.sqrt(np.mean(per**2))),
                        float(np.sqrt(np.mean(np.sum(res[:, :2] ** 2, axis=1)))), per, float(scale))


@dataclass(frozen=True)
class KittiImport:
    t_s: np.ndarray
    truth_enu: np.ndarray  # (N, 4, 4) body axes
    georef: Georeference
    track_lonlatalt: np.ndarray
    origin_alt_m: float
    filled: np.ndarray  # track points the recording filled (left out of the fit)
    offset: int = 0  # the track point of the sequence's frame 0


#: Limits of a believable georeference: KITTI's five drives fit with 0.11–0.37 m RMSE and lever
#: arms of 1.1–2.4 m; another sequence's track fits its poses with ~90 m and a 250 m "lever arm".
MAX_FIT_RESIDUAL_M, MAX_LEVER_ARM_M = 2.0, 5.0

#: Offsets georeferenced when the track is longer than the sequence, and how far apart (frames) they lie: a
#: stop-and-go drive repeats its step lengths within a few frames, and the fit tells those neighbours apart.
OFFSET_CANDIDATES, OFFSET_SEPARATION_FRAMES = 5, 10


def track_offsets(poses_cam: np.ndarray, track_enu_m: np.ndarray, count: int = OFFSET_CANDIDATES,
                  separation: int = OFFSET_SEPARATION_FRAMES) -> list[int]:
    """Where the sequence may begin in the track: up to ``count`` offsets o (track point o is frame 0), best
    first, at least ``separation`` frames apart, ranked by Σ_i (|g_{o+i+1} − g_{o+i}| − |t_{i+1} − t_i|)², the
    track's step lengths (``track_enu_m``: (M, 3) m) against the camera's (``poses_cam``: (N, 4, 4), M ≥ N)."""
    from scipy.signal import correlate

    step_cam = np.linalg.norm(np.diff(poses_cam[:, :3, 3], axis=0), axis=1)
    step_gps = np.linalg.norm(np.diff(np.asarray(track_enu_m, dtype=float), axis=0), axis=1)
    n = len(step_cam)
    if len(step_gps) < n:
        raise ValueError(f"track_offsets: {len(step_gps) + 1} track points for {n + 1} poses")
    if n == 0:
        return [0]
    # Σ (a − b)² = Σ a² − 2 Σ ab + Σ b², each window's Σ a² from a running sum
    sq = np.concatenate(([0.0], np.cumsum(step_gps**2)))
    cost = sq[n:] - sq[:-n] - 2.0 * correlate(step_gps, step_cam, mode="valid") + float(step_cam @ step_cam)
    out: list[int] = []
    for o in np.argsort(cost, kind="stable").tolist():
        if all(abs(o - p) >= separation for p in out):
            out.append(int(o))
            if len(out) == count:
                break
    return out


def import_kitti(poses_path: str | Path, times_path: str | Path, kml_path: str | Path,
                 projection: LocalProjection, offset: int | None = None) -> KittiImport:
    """Read a KITTI sequence and georeference it into ``projection``'s ENU frame. ``offset``: the track point of
    the sequence's frame 0 (None: found, :func:`track_offsets`)."""
    from .formats import read_kitti_poses, read_times

    poses = read_kitti_poses(poses_path)
    t = read_times(times_path)
    if len(t) != len(poses):
        raise FormatError(f"{poses_path}: {len(poses)} poses but {times_path} has {len(t)} times "
                          f"(line {min(len(t), len(poses)) + 1} of the longer file has no partner)")
    full = read_kml_track(kml_path)
    spare = len(full) - len(poses)
    if spare < 0:
        raise FormatError(f"{kml_path}: {len(full)} track points for {len(poses)} poses")
    if offset is not None and not 0 <= offset <= spare:
        raise FormatError(f"{kml_path}: offset {offset} out of range: {len(full)} track points for {len(poses)} "
                          f"poses allow 0-{spare}")
    x, y = projection.to_enu(full[:, 1], full[:, 0])
    enu = np.column_stack([x, y, full[:, 2]])
    candidates = [offset] if offset is not None else track_offsets(poses, enu)
    best: tuple | None = None
    for o in candidates:
        track = full[o:o + len(poses)]
        alt0 = float(track[0, 2])
        gps = np.column_stack([enu[o:o + len(poses), :2], track[:, 2] - alt0])
        filled = filled_points(track)
        geo = georeference(poses, gps, use=~filled)
        if best is None or geo.residual_rmse_m < best[0].residual_rmse_m:
            best = (geo, o, track, alt0, filled)
    assert best is not None
    geo, o, track, alt0, filled = best
    lever_m = float(np.linalg.norm(geo.lever_arm_cam_m))
    if geo.residual_rmse_m > MAX_FIT_RESIDUAL_M or lever_m > MAX_LEVER_ARM_M:
        tried = f"offset {o}" if offset is not None else f"best of offsets {', '.join(map(str, candidates))}"
        raise FormatError(f"{kml_path}: the track does not fit the poses of {poses_path} (residual "
                          f"{geo.residual_rmse_m:.1f} m RMSE, lever arm {lever_m:.1f} m at {tried}; at most "
                          f"{MAX_FIT_RESIDUAL_M:g} and {MAX_LEVER_ARM_M:g} m): the track of another sequence?")
    return KittiImport(t, geo.camera_to_enu(poses), geo, track, alt0, filled, o)


def track_at_camera(imp: KittiImport, projection: LocalProjection) -> np.ndarray:
    """The RTK track moved from the antenna to camera 0 by the fitted lever arm: (N, 3) ENU metres
    (z relative to the first track point's altitude)."""
    g = imp.georef
    # the antenna sits at the lever arm from camera 0: move every fix by it, in ENU
    r_cam = np.einsum("ij,njk,kl->nil", g.rotation.T, imp.truth_enu[:, :3, :3], R_BODY_CAMERA)  # camera rotations
    offset = g.scale * np.einsum("ij,njk,k->ni", g.rotation, r_cam, g.lever_arm_cam_m)
    ax, ay = projection.to_enu(imp.track_lonlatalt[:, 1], imp.track_lonlatalt[:, 0])
    return np.column_stack([np.asarray(ax) - offset[:, 0], np.asarray(ay) - offset[:, 1],
                            imp.track_lonlatalt[:, 2] - imp.origin_alt_m - offset[:, 2]])


def write_import(out: str | Path, imp: KittiImport, projection: LocalProjection, map_path: str,
                 gps_sigma_m: float = 0.05, gps_at_camera: bool = True) -> Path:
    """``truth.tum``, ``truth.csv``, ``gps.csv`` (the RTK track, moved from the antenna to camera 0 by
    the fitted lever arm unless ``gps_at_camera`` is false) and ``import.json`` (the fit)."""
    from scipy.spatial.transform import Rotation

    d = Path(out)
    d.mkdir(parents=True, exist_ok=True)
    xyz = imp.truth_enu[:, :3, 3]
    q = Rotation.from_matrix(imp.truth_enu[:, :3, :3]).as_quat()
    write_tum(d / "truth.tum", imp.t_s, xyz, q, header="KITTI ground truth, camera 0 with body axes, map ENU frame")
    yaw = Rotation.from_matrix(imp.truth_enu[:, :3, :3]).as_euler("ZYX")[:, 0]
    step = np.hypot(*np.diff(xyz[:, :2], axis=0).T)
    speed = np.gradient(np.concatenate(([0.0], np.cumsum(step))), imp.t_s)
    lat, lon = projection.to_geo(xyz[:, 0], xyz[:, 1])
    with open(d / "truth.csv", "w") as f:
        f.write("t,x,y,z,yaw,speed,lat,lon,sumo_edge,osm_way,in_tunnel,sumo_lane,distance_m,sumo_speed\n")
        dist = np.concatenate(([0.0], np.cumsum(step)))
        for i in range(len(imp.t_s)):
            f.write(f"{imp.t_s[i]:.6f},{xyz[i, 0]:.4f},{xyz[i, 1]:.4f},{xyz[i, 2]:.4f},{yaw[i]:.6f},{speed[i]:.4f},"
                    f"{lat[i]:.9f},{lon[i]:.9f},,,0,,{dist[i]:.3f},\n")
    tr = imp.track_lonlatalt.copy()
    if gps_at_camera:
        cam = track_at_camera(imp, projection)
        lat_c, lon_c = projection.to_geo(cam[:, 0], cam[:, 1])
        tr[:, 1], tr[:, 0], tr[:, 2] = lat_c, lon_c, cam[:, 2] + imp.origin_alt_m
    write_gps_csv(d / "gps.csv", imp.t_s, tr[:, 1], tr[:, 0], tr[:, 2], np.full(len(tr), gps_sigma_m))
    g = imp.georef
    info = {"map": map_path, "frames": int(len(imp.t_s)), "track_offset": imp.offset,
            "residual_rmse_m": g.residual_rmse_m, "residual_rmse_xy_m": g.residual_rmse_xy_m,
            "residual_max_m": float(g.residuals_m.max()),
            "lever_arm_cam_m": g.lever_arm_cam_m.tolist(), "rotation": g.rotation.tolist(),
            "translation_m": g.translation.tolist(), "origin_alt_m": imp.origin_alt_m,
            "filled_track_points": int(imp.filled.sum()),
            "gps_at": "camera" if gps_at_camera else "antenna",
            "note": "truth is camera 0 with body axes; gps.csv is the RTK track, at camera 0 (moved by the lever arm) "
                    "or at the antenna as gps_at says"}
    (d / "import.json").write_text(json.dumps(info, indent=2) + "\n")
    return d
