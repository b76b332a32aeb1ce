"""The pipelines every command shares: one scenario simulated (a SUMO drive or a recorded one, then
the sensors), fused (baseline and Map-Fusion), evaluated and written as a run directory (DESIGN
"File formats", contract); and the engine on recorded files (``mapfusion fuse``)."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapfusion.formats import GpsFixes, write_tum
from mapfusion.geometry import cumulative_length
from mapfusion.metrics import (associate, ate, delocalized, match_rate, online_error, relocalisation_m, rpe_per_100m,
                               zone_rmse)
from mapfusion.config import FusionConfig
from mapfusion.roadmap import RoadMap
from mapfusion.replay import (FusionResult, MotionSamples, OdometryFormat, OdometryFrame, fuse, poses_to_arrays,
                              read_odometry)

from .results import Estimator, ate_key, delocalized_key, estimator_metrics, non_finite_to_none

from sim.drive import DriveResult, run_drive
from sim.network import build_network
from sim.recorded import RecordedDrive, load_recorded, recorded_gps
from .rundir import write_recorded_truth, write_sensors, write_truth
from sim.scenario import GpsSource, Scenario
from sim.sensors import SensorData, Truth, synthesise, under_bridges


@dataclass
class RunOutcome:
    metrics: dict
    drive: DriveResult | None  # None for a recorded drive
    truth: Truth
    sensors: SensorData
    baseline: FusionResult
    mapfusion: FusionResult
    road: RoadMap
    others: dict = dataclasses.field(default_factory=dict)  # name → estimators.Track of the [[estimators]]


def _online_arrays(res: FusionResult):
    ok = [i for i, p in enumerate(res.online) if p is not None]
    xyz = np.array([[res.online[i].x(), res.online[i].y(), res.online[i].z()] for i in ok]).reshape(-1, 3)
    yaw = np.array([res.online[i].rotation().yaw() for i in ok])
    return res.t_s[ok], xyz, yaw, ok


def online_error_along(res: FusionResult, truth: Truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The online estimate's frames against the truth: (time s, distance the truth has driven m, horizontal
    error m), one entry per estimated frame."""
    t, xyz, _, _ = _online_arrays(res)
    ia, ib = associate(t, truth.t_s)
    driven = cumulative_length(np.column_stack([truth.x_m, truth.y_m]))
    return t[ia], driven[ib], np.hypot(xyz[ia, 0] - truth.x_m[ib], xyz[ia, 1] - truth.y_m[ib])


def kidnap_from_m(truth: Truth, kidnap) -> float:
    """The distance the truth has driven at a kidnap (where ``relocalisation_m`` counts from)."""
    driven = cumulative_length(np.column_stack([truth.x_m, truth.y_m]))
    k = int(np.searchsorted(truth.t_s, kidnap.t_s - 1e-9))
    return float(driven[min(k, len(driven) - 1)])


def _kidnap_metrics(res: FusionResult, truth: Truth, kidnap) -> dict:
    """``relocalised`` and ``relocalisation_m`` of a kidnapped drive (issue 17; null without a kidnap): the
    distance driven from the kidnap until Map-Fusion's online error stays under 10 m for the next 100 m."""
    if kidnap is None:
        return {"relocalised": None, "relocalisation_m": None}
    t_est, driven_m, err = online_error_along(res, truth)
    from_m = kidnap_from_m(truth, kidnap)
    r = relocalisation_m(driven_m, err, from_m)
    after = err[driven_m >= from_m + r] if r is not None else np.empty(0)
    # a re-anchoring more than 25 m from the truth is a wrong convergence: how far it stayed wrong
    wrong_m = []
    for t_r, _ in res.engine.relocalised_at:
        i = int(np.searchsorted(t_est, t_r - 1e-9))
        if i < len(err) and err[i] > 25.0:
            back = np.flatnonzero(err[i:] <= 25.0)
            end = i + int(back[0]) if back.size else len(err) - 1
            wrong_m.append(float(driven_m[end] - driven_m[i]))
    return {"relocalised": r is not None, "relocalisation_m": r, "kidnap": kidnap.kind,
            "kidnap_distance_m": kidnap.distance_m, "kidnap_heading_deg": math.degrees(kidnap.heading_rad),
            "online_mean_after_relocalisation_m": float(np.mean(after)) if after.size else None,
            "wrong_relocalisations": len(wrong_m), "wrong_relocalisation_max_m": max(wrong_m, default=0.0)}


def _evaluate(res: FusionResult, truth: Truth, estimator: Estimator, deloc_m: float) -> dict:
    t, xyz, yaw, _ = _online_arrays(res)
    return _evaluate_track(t, xyz, yaw, truth, estimator, deloc_m)


def _evaluate_track(t, xyz, yaw, truth: Truth, estimator: Estimator | str, deloc_m: float) -> dict:
    e = truth
    ia, ib = associate(t, e.t_s)
    gt = np.column_stack([e.x_m, e.y_m, e.z_m])[ib]
    a = ate(gt, xyz[ia])
    on = online_error(gt, e.yaw_rad[ib], xyz[ia], t[ia])
    tun = zone_rmse(gt, xyz[ia], e.visually_degraded[ib])
    rpe = rpe_per_100m(gt, e.yaw_rad[ib], xyz[ia], yaw[ia])
    return estimator_metrics(estimator, a, delocalized(a, deloc_m), on, tun, rpe)


def motion_of(sensors: SensorData) -> MotionSamples | None:
    """The wheel speed and the IMU's yaw rate (gyro z) for the engine, where the odometry kind has a wheel."""
    if sensors.wheel is None:
        return None
    return MotionSamples(sensors.wheel.t_s, sensors.wheel.speed_mps, sensors.imu.t_s, sensors.imu.gyro_radps[:, 2])


def fixes_of(sensors: SensorData, road: RoadMap) -> GpsFixes:
    g = sensors.gps
    lat, lon = road.projection.to_geo(g.x_m, g.y_m)
    return GpsFixes(g.t_s, np.asarray(lat), np.asarray(lon), np.asarray(g.alt_m), g.sigma_m)


@dataclass
class Simulation:
    """A scenario's drive and sensors: what a sweep simulates once and fuses many times."""

    sc: Scenario
    road: RoadMap
    truth: Truth
    drive: DriveResult | None  # None for a recorded drive
    sensors: SensorData
    route_length_m: float
    recorded: RecordedDrive | None = None


def simulate_scenario(sc: Scenario, progress=None) -> Simulation:
    """Drive ``sc`` in SUMO (or load its recorded drive) and synthesise its sensors."""
    road = RoadMap.from_osm(sc.map)
    if sc.truth:  # a recorded drive: no SUMO
        rec = load_recorded(sc.truth, sc, road)
        sensors = synthesise(sc, rec.truth, recorded_gps(rec, sc.gps) if sc.gps.source is GpsSource.recorded else None)
        return Simulation(sc, road, rec.truth, None, sensors, rec.length_m, rec)
    net = build_network(sc.map)
    drive = run_drive(sc, road, net, progress=progress)
    bridges = under_bridges(road, drive.ego.x_m, drive.ego.y_m, drive.ego.osm_way, sc.gps.bridge_lane_width_m)
    truth = Truth.from_track(drive.ego, bridges, sc.gps)
    return Simulation(sc, road, truth, drive, synthesise(sc, truth), drive.route_length_m)


def map_resets(sim: Simulation) -> tuple[int, bool]:
    """The simulated odometry's map resets, and whether they de-localise the run: an ``orb-vio`` reset does,
    as the paper counts ORB-SLAM3's."""
    n = sum(1 for _, what in sim.sensors.odometry.events if what == "map_reset")
    return n, n > 0 and sim.sc.odometry.kind.resets_delocalise


def fuse_and_evaluate(sim: Simulation, cfg: FusionConfig, baseline: FusionResult | None = None
                      ) -> tuple[dict, FusionResult, FusionResult]:
    """The baseline (map priors off; pass one to reuse it) and Map-Fusion with ``cfg`` on the
    simulation's sensors, both evaluated: (metrics, baseline, Map-Fusion)."""
    sc, truth, sensors = sim.sc, sim.truth, sim.sensors
    road = sim.road
    fixes = fixes_of(sensors, road)
    odo, motion = sensors.odometry, motion_of(sensors)
    base = baseline or fuse(road, odo.t_s, odo.poses, fixes, dataclasses.replace(cfg, use_map=False), motion=motion)
    t0 = time.perf_counter()
    mf = fuse(road, odo.t_s, odo.poses, fixes, cfg, motion=motion)
    fusion_fps = len(odo.t_s) / max(time.perf_counter() - t0, 1e-9)
    metrics: dict = {
        "scenario": sc.name, "seed": sc.seed, "map": Path(sc.map).name, "weather": sc.weather.kind.value,
        "odometry": sc.odometry.kind.value, "gps_mode": sc.gps.mode.value,
        "route_length_m": sim.route_length_m, "duration_s": float(truth.t_s[-1] - truth.t_s[0]),
        "frames": int(len(truth)), "driven_m": float(np.sum(np.hypot(np.diff(truth.x_m), np.diff(truth.y_m)))),
    }
    if sim.recorded is not None:
        metrics["recorded"] = sc.truth
        if sim.recorded.georef_residual_m is not None:
            metrics["georef_residual_m"] = sim.recorded.georef_residual_m
    if not (base.engine.initialised and mf.engine.initialised):
        metrics.update({"error": "the engine never initialised (too few GPS fixes while moving)"})
    else:
        mb = _evaluate(base, truth, Estimator.odometry, cfg.delocalization_m)
        mm = _evaluate(mf, truth, Estimator.mapfusion, cfg.delocalization_m)
        metrics.update(mb)
        metrics.update(mm)
        metrics["ate_reduction_m"] = mb[ate_key(Estimator.odometry)] - mm[ate_key(Estimator.mapfusion)]
        metrics["odometry_map_resets"], lost = map_resets(sim)
        if lost:
            metrics[delocalized_key(Estimator.odometry)] = metrics[delocalized_key(Estimator.mapfusion)] = True
        # match rate: frames outside junctions whose matched way is the way SUMO drives on (a
        # recorded drive has no such truth: null)
        metrics["match_rate"] = metrics["match_rate_road"] = None
        if sim.drive is not None:
            frames, matched = sensors.odometry.frame_index, np.asarray(mf.engine.matched_way)
            if motion is not None:  # wheel + gyro add frames where the odometry has none: by time, then
                ia, frames = associate(mf.t_s, truth.t_s)
                matched = matched[ia]
            true_way = sim.drive.ego.osm_way[frames]
            sel = matched >= 0
            # the contract's match rate (the very way SUMO drives on), and the same counting a way that
            # merely continues it through a non-junction vertex (OSM splits roads anywhere) as a match
            if sel.any():
                metrics["match_rate"] = match_rate(true_way[sel], matched[sel])
                metrics["match_rate_road"] = match_rate(true_way[sel], matched[sel], road.continuations())
        c = mf.engine.counters
        metrics.update({"map_priors": c.map_priors, "gps_used": c.gps_used,
                        "gps_rejected": c.gps_rejected, "gps_rejected_gate": c.gps_rejected_gate,
                        "gps_rejected_time": c.gps_rejected_time, "gps_rejected_invalid": c.gps_rejected_invalid,
                        "recoveries": c.recoveries, "odometry_jumps": c.odometry_jumps,
                        "gps_relocalisations": c.gps_relocalisations, "gps_rescales": c.gps_rescales,
                        "lost_events": c.lost_events, "lost_s": mf.engine.lost_s,
                        "map_relocalisations": c.map_relocalisations,
                        "road_fixes": c.road_fixes, "road_fixes_gated": c.road_fixes_gated,
                        "scale": mf.engine.scale, "initialised_at_s": mf.engine.initialised_at,
                        "odometry_sigma_factor": mf.engine.odometry_sigma_factor})
        metrics.update(_kidnap_metrics(mf, truth, sensors.kidnap))
        if motion is not None:  # wheel + gyro runs only: the vo and vio rows keep their keys
            metrics.update({"odometry_vetoed": c.odometry_vetoed, "wheel_frames": c.wheel_frames,
                            "wheel_scale": mf.engine.wheel_scale, "wheel_scale_true": 1.0 / (1.0 + sensors.wheel.scale_error),
                            "gyro_bias_radps": mf.engine.gyro_bias_radps})
    metrics["fusion_frames_per_s"] = fusion_fps
    return non_finite_to_none(metrics), base, mf


def run_scenario(sc: Scenario, out_dir: str | Path | None = None, progress=None, plot: bool = True) -> RunOutcome:
    """Simulate ``sc``, run the baseline (map priors off) and Map-Fusion on the same sensors and
    GPS, evaluate both, and (with ``out_dir``) write every file of the run directory."""
    sim = simulate_scenario(sc, progress)
    metrics, base, mf = fuse_and_evaluate(sim, sc.mapfusion)
    others = score_estimators(sim, metrics) if sc.estimators and "error" not in metrics else {}
    outcome = RunOutcome(metrics, sim.drive, sim.truth, sim.sensors, base, mf, sim.road, others)
    if out_dir is not None:
        write_run(Path(out_dir), sc, outcome, plot=plot)
    return outcome


def score_estimators(sim: Simulation, metrics: dict) -> dict:
    """The scenario's [[estimators]] on the simulation's inputs (those Map-Fusion got), each scored into
    ``metrics`` (``ate_<name>_m`` ...) or, when it failed, its one line in ``metrics["estimator_errors"]``;
    ``metrics["estimators"]`` lists their names. Returns name → the estimate scored."""
    from .estimators import EstimatorError, run_estimator

    sensors, road = sim.sensors, sim.road
    fixes, motion = fixes_of(sensors, road), motion_of(sensors)
    imu = (sensors.imu.t_s, sensors.imu.accel_mps2, sensors.imu.gyro_radps)
    odo = sensors.odometry
    tracks, errors = {}, {}
    for spec in sim.sc.estimators:
        try:
            tr = run_estimator(spec, road, sim.sc.map, odo.t_s, odo.poses, fixes, motion, imu)
            metrics.update(_evaluate_track(tr.t_s, tr.xyz_m, tr.yaw_rad, sim.truth, spec.name,
                                           sim.sc.mapfusion.delocalization_m))
            tracks[spec.name] = tr
        except EstimatorError as exc:
            errors[spec.name] = str(exc)
    metrics["estimators"] = [s.name for s in sim.sc.estimators]
    if errors:
        metrics["estimator_errors"] = errors
    metrics.update(non_finite_to_none({k: v for k, v in metrics.items() if isinstance(v, float)}))
    return tracks


def write_simulation(d: Path, sim: Simulation) -> None:
    """The simulated part of a run directory: scenario.toml, truth.tum, truth.csv and the sensors."""
    if sim.drive is not None:
        write_truth(d, sim.sc, sim.drive)
    else:
        t = sim.truth
        write_recorded_truth(d, sim.sc, t.t_s, np.column_stack([t.x_m, t.y_m, t.z_m]), t.yaw_rad, t.visually_degraded,
                             sim.road.projection)
    write_sensors(d, sim.sensors, sim.road.projection)


def write_run(d: Path, sc: Scenario, o: RunOutcome, plot: bool = True) -> None:
    """Every file of a run directory."""
    write_simulation(d, Simulation(sc, o.road, o.truth, o.drive, o.sensors, math.nan))
    for name, res in (("estimate_odometry.tum", o.baseline), ("estimate_mapfusion.tum", o.mapfusion)):
        _write_online(res, d / name, f"{name[:-4]}: online (causal) estimates, map ENU frame")
    for other, tr in o.others.items():
        from scipy.spatial.transform import Rotation

        q = Rotation.from_euler("z", np.asarray(tr.yaw_rad)[:, None]).as_quat()
        write_tum(d / f"estimate_{other}.tum", tr.t_s, tr.xyz_m, q,
                  header=f"estimate_{other}: the estimator {other}'s estimates (yaw only), map ENU frame")
    (d / "metrics.json").write_text(json.dumps(o.metrics, indent=2) + "\n")
    eng = o.mapfusion.engine
    events = {"map_prior_t": [float(t) for t in eng.map_prior_times()], "counters": eng.counters.as_dict(),
              "initialised_at_s": eng.initialised_at, "scale": eng.scale, "scale_sigma": eng.scale_sigma,
              "map_relocalisations": [{"t_s": t, "searched_m": m} for t, m in eng.relocalised_at]}
    (d / "fusion_events.json").write_text(json.dumps(events, indent=2) + "\n")
    from .export import write_geojson

    write_geojson(d, d / "run.geojson", road=o.road)
    if plot:
        from .plot import plot_run

        plot_run(d, d / "plot.png", road=o.road)


# ----------------------------------------------------------------------------- recorded data
@dataclass(frozen=True)
class RecordedInputs:
    """What ``mapfusion fuse`` reads: the map, the odometry and optional GPS and IMU files."""

    map: str
    odometry: Path
    odometry_format: OdometryFormat = OdometryFormat.tum
    odometry_frame: OdometryFrame = OdometryFrame.body
    times: Path | None = None
    gps: Path | None = None
    gps_until_s: float | None = None  # fixes only this long from the first odometry frame
    imu: Path | None = None  # its gyro's z axis is the yaw rate fused with --wheel; without a wheel only checked
    wheel: Path | None = None  # wheel speed (t,speed_mps), fused with the IMU's yaw rate (issue 18)
    start_region: tuple[float, float, float] | None = None  # (lat, lon, radius_m): a cold start (issue 17)


def fuse_recorded(inputs: RecordedInputs, cfg: FusionConfig, progress=None, on_frame=None) -> FusionResult:
    """The engine on recorded files (InputError / FormatError on bad input); ``on_frame(engine)``
    after every frame."""
    t_odo, poses = read_odometry(inputs.odometry, inputs.odometry_format, inputs.times, inputs.odometry_frame)
    road, fixes, motion = _recorded_map_and_gps(inputs, t_odo[[0, -1]])
    return fuse(road, t_odo, poses, fixes, cfg, progress=progress, on_frame=on_frame, motion=motion,
                start_region=inputs.start_region)


def _recorded_map_and_gps(inputs: RecordedInputs, span_s: np.ndarray):
    """The road map and the fixes (up to --gps-until-s), checked against each other; the IMU file
    read through and checked, and with a wheel file both as the engine's second motion source
    (refused when their times miss the odometry's ``span_s``, first and last)."""
    from mapfusion.formats import FormatError, check_imu_csv, read_gps_csv, read_imu_csv, read_wheel_csv

    fixes = read_gps_csv(inputs.gps) if inputs.gps is not None else None
    motion = None
    if inputs.wheel is not None:
        if inputs.imu is None:
            raise FormatError(f"{inputs.wheel}: wheel speed needs the IMU's yaw rate (--imu)")
        t_w, v = read_wheel_csv(inputs.wheel)
        t_i, _, gyro = read_imu_csv(inputs.imu)
        for path, t in ((inputs.wheel, t_w), (inputs.imu, t_i)):
            if len(t) < 2 or t[-1] <= span_s[0] or t[0] >= span_s[1]:
                raise FormatError(f"{path}: its times ({t[0]:.3f}–{t[-1]:.3f} s) miss the odometry's "
                                  f"({span_s[0]:.3f}–{span_s[1]:.3f} s)")
        motion = MotionSamples(t_w, v, t_i, gyro[:, 2])
    elif inputs.imu is not None:
        check_imu_csv(inputs.imu)
    road, fixes = _map_and_fixes(inputs.map, fixes, float(span_s[0]), inputs.gps_until_s, f"{inputs.gps}: the GPS fixes")
    if inputs.start_region is not None:
        lat, lon, _ = inputs.start_region
        road.check_covers(np.column_stack(road.projection.to_enu(np.array([lat]), np.array([lon]))),
                          f"--start-region {lat},{lon} on the map {inputs.map}")
    return road, fixes, motion


def _map_and_fixes(map_name: str, fixes: GpsFixes | None, t0_s: float, gps_until_s: float | None, what: str):
    """The road map, and the fixes up to ``gps_until_s`` after ``t0_s``, refused when they lie off it."""
    from mapfusion.maps import resolve_map

    if fixes is not None and gps_until_s is not None:
        fixes = fixes.until(t0_s + gps_until_s)
    road = RoadMap.from_osm(resolve_map(map_name))
    if fixes is not None and len(fixes):
        road.check_covers(np.column_stack(road.projection.to_enu(fixes.lat_deg, fixes.lon_deg)),
                          f"{what} on the map {map_name}")
    return road, fixes


#: Frames converted and written at a time by the streamed writers.
WRITE_BATCH = 1000


class _StreamedTum:
    """Poses handed out by the engine, written to a TUM file in batches (numbers as write_tum's)."""

    def __init__(self, path: Path, header: str) -> None:
        from mapfusion.formats import TumWriter

        self.writer = TumWriter(path, header)
        self.t: list[float] = []
        self.poses: list = []

    def add(self, t: float, pose) -> None:
        if pose is not None:
            self.t.append(t)
            self.poses.append(pose)
            if len(self.t) >= WRITE_BATCH:
                self.flush()

    def flush(self) -> None:
        if self.t:
            xyz, q = poses_to_arrays(self.poses)
            self.writer.write(self.t, xyz, q)
            self.t, self.poses = [], []


def fuse_recorded_to_files(inputs: RecordedInputs, cfg: FusionConfig, out: Path, smoothed: Path | None = None,
                           label: str = "", progress=None):
    """``mapfusion fuse``: the engine over recorded files of any length in flat memory, the online
    estimate (and the smoothed trajectory) written as they become final. The files appear only when
    the engine initialised. Returns (engine, poses written)."""
    from mapfusion.replay import fuse_streaming, odometry_times

    t_all = odometry_times(inputs.odometry, inputs.odometry_format, inputs.times)  # checks the whole file
    road, fixes, motion = _recorded_map_and_gps(inputs, t_all[[0, -1]])
    online = _StreamedTum(out, f"Map-Fusion online estimate{label}")
    smooth = _StreamedTum(smoothed, "Map-Fusion smoothed trajectory") if smoothed is not None else None
    writers = [w for w in (online, smooth) if w is not None]

    def on_final(t: float, pose, smoothed_pose) -> None:
        online.add(t, pose)
        if smooth is not None:
            smooth.add(t, smoothed_pose)

    try:
        eng = fuse_streaming(road, inputs.odometry, inputs.odometry_format, inputs.times, inputs.odometry_frame,
                             fixes, cfg, on_final, progress, t_all, motion, inputs.start_region)
        for w in writers:
            w.flush()
    except BaseException:
        for w in writers:
            w.writer.discard()
        raise
    for w in writers:
        if eng.initialised:
            w.writer.commit()
        else:
            w.writer.discard()
    return eng, online.writer.count


def _write_online(res: FusionResult, path: Path, header: str) -> int:
    """The frames' causal estimates as TUM (nothing when there is none); returns the poses written."""
    t, _, _, ok = _online_arrays(res)
    if len(ok):
        xyz, q = poses_to_arrays([res.online[i] for i in ok])
        write_tum(path, t, xyz, q, header=header)
    return len(ok)


def write_estimates(res: FusionResult, out: Path, smoothed: Path | None = None, label: str = "") -> int:
    """The online estimate (and optionally the smoothed trajectory) as TUM; returns the poses written."""
    n = _write_online(res, out, f"Map-Fusion online estimate{label}")
    if smoothed is not None:
        ts = sorted(res.smoothed)
        sxyz, sq = poses_to_arrays([res.smoothed[t] for t in ts])
        write_tum(smoothed, np.asarray(ts), sxyz, sq, header="Map-Fusion smoothed trajectory")
    return n


def evaluate_files(truth: Path, estimate: Path, max_dt_s: float = 0.02, delocalization_m: float = 20.0,
                   fit_scale: bool = False) -> dict:
    """``mapfusion evaluate``: ATE, online error (lateral, longitudinal), RPE per 100 m and KITTI's
    t_err / r_err of a TUM estimate against a TUM truth (InputError / FormatError on bad input);
    ``fit_scale``: KITTI's errors after one fitted global scale (a monocular odometry's)."""
    from mapfusion.errors import InputError
    from mapfusion.formats import quaternion_to_yaw, read_tum, tum_to_matrices
    from mapfusion.metrics import global_scale, kitti_errors

    tt, xt, qt = read_tum(truth)
    te, xe, qe = read_tum(estimate)
    ia, ib = associate(te, tt, max_dt_s)
    if len(ia) < 3:
        raise InputError(f"{estimate}: only {len(ia)} poses match {truth} in time (within {max_dt_s} s)")
    a = ate(xt[ib], xe[ia])
    yt, ye = quaternion_to_yaw(qt[ib]), quaternion_to_yaw(qe[ia])
    on = online_error(xt[ib], yt, xe[ia], te[ia])
    rpe = rpe_per_100m(xt[ib], yt, xe[ia], ye)
    scale = global_scale(xt[ib], xe[ia]) if fit_scale else 1.0
    k = kitti_errors(tum_to_matrices(xt[ib], qt[ib]), tum_to_matrices(xe[ia], qe[ia]), scale)
    return {"frames": int(len(ia)), "ate_m": a, "delocalized": delocalized(a, delocalization_m),
            "online_rmse_m": on.rmse_m, "online_max_m": on.max_m, "online_lateral_rmse_m": on.lateral_rmse_m,
            "online_longitudinal_rmse_m": on.longitudinal_rmse_m, "online_end_m": on.end_m, "rpe_per_100m_m": rpe,
            "kitti_t_err_percent": k.t_err_percent, "kitti_r_err_deg_per_100m": k.r_err_deg_per_100m,
            "kitti_segments": k.segments, "kitti_scale": scale}


@dataclass(frozen=True)
class BagInputs:
    """What ``mapfusion fuse --bag`` reads: the map and the bag's topics."""

    map: str
    bag: Path
    odometry_topic: str
    gps_topic: str | None = None
    imu_topic: str | None = None
    gps_until_s: float | None = None
    wheel_topic: str | None = None  # fused with the IMU topic's yaw rate (issue 18)
    use_covariance: bool = True  # the odometry's published pose covariance sets odometry_sigma_per_m


def fuse_bag(inputs: BagInputs, cfg: FusionConfig, progress=None):
    """The engine on a ROS bag's topics (InputError / BagError on bad input): (FusionResult, BagData,
    each frame's positional σ from the engine's latest marginal, metres)."""
    from mapfusion.bags import read_bag, sigma_per_m_from_covariance

    data = read_bag(inputs.bag, inputs.odometry_topic, inputs.gps_topic, inputs.imu_topic, inputs.wheel_topic)
    if inputs.use_covariance and data.position_var_m2 is not None:
        s = sigma_per_m_from_covariance(data.poses, data.position_var_m2)
        if s is not None:  # the odometry's own covariance sets the engine's σ per metre
            cfg = dataclasses.replace(cfg, odometry_sigma_per_m=s)
    road, fixes = _map_and_fixes(inputs.map, data.gps, float(data.t_s[0]), inputs.gps_until_s,
                                 f"{inputs.bag}: the GPS fixes of {inputs.gps_topic}")
    motion = None
    if data.wheel is not None and data.imu is not None:  # wheel speed with the IMU's yaw rate (issue 18)
        motion = MotionSamples(data.wheel[0], data.wheel[1], data.imu[0], data.imu[2][:, 2])
    sigmas: list[float] = []
    res = fuse(road, data.t_s, data.poses, fixes, cfg, progress=progress,
               on_frame=lambda e: sigmas.append(e.position_sigma_m), motion=motion)
    return res, data, np.asarray(sigmas)  # res.engine.cfg holds the σ the covariance set


def write_estimate_bag(path: Path, kind, res: FusionResult, sigmas_m: np.ndarray) -> int:
    """The online estimate as nav_msgs/Odometry (frame map, child base_link; the position
    covariance from the engine's marginal σ at each frame) and the map priors as a MarkerArray."""
    from mapfusion.bags import write_bag

    t, xyz, yaw, ok = _online_arrays(res)
    poses = np.array([res.online[i].matrix() for i in ok]).reshape(-1, 4, 4)
    cov = np.zeros((len(ok), 6, 6))
    s2 = np.square(np.asarray(sigmas_m, dtype=float)[ok]) if len(sigmas_m) == len(res.online) else np.zeros(len(ok))
    cov[:, 0, 0] = cov[:, 1, 1] = s2
    prior_t = np.asarray(res.engine.map_prior_times())
    keep = np.isin(t, prior_t)
    write_bag(path, kind, (t, poses), frame="map", child_frame="base_link", odometry_topic="/mapfusion/odometry",
              covariances=cov, markers=("/mapfusion/map_priors", t[keep], xyz[keep]))
    return len(ok)
