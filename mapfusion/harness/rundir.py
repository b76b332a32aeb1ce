"""Writing a run directory (DESIGN "File formats", contract): scenario.toml, truth.tum, truth.csv."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from mapfusion.formats import (matrices_to_tum, write_gps_csv, write_imu_csv, write_tum, write_wheel_csv,
                               yaw_to_quaternion)

from sim.drive import DriveResult, Track
from sim.scenario import Scenario
from sim.sensors import SensorData

#: truth.csv columns: the contract's first, then this test bed's additions at the end.
TRUTH_COLUMNS = ("t", "x", "y", "z", "yaw", "speed", "lat", "lon", "sumo_edge", "osm_way", "in_tunnel",
                 "sumo_lane", "distance_m", "sumo_speed")


def _rows(track: Track, vehicle_column: bool = False):
    for i in range(len(track)):
        row = [
            f"{track.t_s[i]:.3f}", f"{track.x_m[i]:.4f}", f"{track.y_m[i]:.4f}", f"{track.z_m[i]:.4f}",
            f"{track.yaw_rad[i]:.6f}", f"{track.speed_mps[i]:.4f}", f"{track.lat_deg[i]:.9f}",
            f"{track.lon_deg[i]:.9f}", track.sumo_edge[i],
            "" if track.osm_way[i] < 0 else str(int(track.osm_way[i])),
            "1" if track.in_tunnel[i] else "0", track.sumo_lane[i], f"{track.distance_m[i]:.3f}",
            f"{track.sumo_speed_mps[i]:.4f}",
        ]
        yield ([track.vehicle] + row) if vehicle_column else row


def write_truth(run_dir: str | Path, sc: Scenario, drive: DriveResult) -> Path:
    """Write ``scenario.toml`` (fully resolved), ``truth.tum``, ``truth.csv`` and, in fleet mode,
    ``fleet.csv`` (one row per vehicle and step), plus ``drive.json`` (route and timing)."""
    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    (d / "scenario.toml").write_text(sc.to_toml())
    ego = drive.ego
    xyz = [(x, y, z) for x, y, z in zip(ego.x_m, ego.y_m, ego.z_m)]
    write_tum(d / "truth.tum", ego.t_s, xyz, yaw_to_quaternion(ego.yaw_rad),
              header=f"ground truth of {sc.name} (SUMO, map ENU frame)")
    with open(d / "truth.csv", "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(TRUTH_COLUMNS)
        w.writerows(_rows(ego))
    if drive.fleet:
        with open(d / "fleet.csv", "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(("vehicle",) + TRUTH_COLUMNS)
            for track in drive.fleet.values():
                w.writerows(_rows(track, vehicle_column=True))
    info = {"route_edges": drive.route_edges, "route_length_m": drive.route_length_m, "frames": len(ego),
            "duration_s": float(ego.t_s[-1] - ego.t_s[0]) if len(ego) else 0.0,
            "driven_m": float(ego.distance_m[-1]) if len(ego) else 0.0, "vehicles": drive.vehicles}
    (d / "drive.json").write_text(json.dumps(info, indent=2) + "\n")
    return d


def write_sensors(run_dir: str | Path, sensors: SensorData, projection) -> Path:
    """Write ``odometry.tum`` (the odometry's own frame, from identity), ``gps.csv``, ``imu.csv`` (and
    ``wheel.csv`` where the odometry kind has a wheel),
    plus ``sensor_events.json`` (re-initialisations, map resets, rain episodes, dropped frames)."""
    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    odo = sensors.odometry
    xyz, q = matrices_to_tum(odo.poses)
    write_tum(d / "odometry.tum", odo.t_s, xyz, q, header="simulated odometry, its own frame (starts at identity)")
    g = sensors.gps
    lat, lon = projection.to_geo(g.x_m, g.y_m)
    write_gps_csv(d / "gps.csv", g.t_s, lat, lon, g.alt_m, g.sigma_m)
    write_imu_csv(d / "imu.csv", sensors.imu.t_s, sensors.imu.accel_mps2, sensors.imu.gyro_radps)
    if sensors.wheel is not None:
        write_wheel_csv(d / "wheel.csv", sensors.wheel.t_s, sensors.wheel.speed_mps)
    events = {
        "events": [{"t": t, "kind": k} for t, k in odo.events],
        "dropped_frames": int(odo.dropped.sum()),
        "rain_episode_frames": int(odo.rain_episode.sum()),
        "gps_fixes": int(len(g.t_s)),
        "gps_outliers": int(g.outlier.sum()),
        "odometry_params": {k: v for k, v in sensors.params.__dict__.items()},
    }
    if sensors.kidnap is not None:  # issue 17: what was drawn
        events["kidnap"] = dict(sensors.kidnap.__dict__)
    (d / "sensor_events.json").write_text(json.dumps(events, indent=2) + "\n")
    return d


def write_recorded_truth(run_dir: str | Path, sc: Scenario, t_s, xyz, yaw, in_zone, projection) -> Path:
    """``scenario.toml``, ``truth.tum`` and a ``truth.csv`` (no SUMO columns) for a recorded truth."""
    import numpy as np

    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    (d / "scenario.toml").write_text(sc.to_toml())
    write_tum(d / "truth.tum", t_s, xyz, yaw_to_quaternion(yaw), header=f"recorded ground truth of {sc.name}, map ENU frame")
    step = np.hypot(*np.diff(xyz[:, :2], axis=0).T)
    dist = np.concatenate(([0.0], np.cumsum(step)))
    speed = np.gradient(dist, t_s) if len(t_s) > 1 else np.zeros(len(t_s))
    lat, lon = projection.to_geo(xyz[:, 0], xyz[:, 1])
    with open(d / "truth.csv", "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(TRUTH_COLUMNS)
        for i in range(len(t_s)):
            w.writerow([f"{t_s[i]:.6f}", f"{xyz[i, 0]:.4f}", f"{xyz[i, 1]:.4f}", f"{xyz[i, 2]:.4f}", f"{yaw[i]:.6f}",
                        f"{speed[i]:.4f}", f"{lat[i]:.9f}", f"{lon[i]:.9f}", "", "", "1" if in_zone[i] else "0", "",
                        f"{dist[i]:.3f}", ""])
    return d
