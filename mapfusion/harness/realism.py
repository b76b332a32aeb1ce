"""How real the simulated odometry is (issue 22): its error statistics beside a real VO's on the same
drives, and whether Map-Fusion's verdict (better or worse than no map) on the simulated odometry
agrees with its verdict on the real output.

The real outputs are ``$MAPFUSION_DATA/vo/{cvo_stereo,trianflow}_NN.txt`` on the KITTI drives
``$MAPFUSION_DATA/kitti/NN``; the presets that model them are ``vo`` (stereo) and ``mono``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: The development drives and, per preset, the real output it is fitted on.
DRIVES = ("00", "01", "02", "05", "07")
REAL_METHOD = {"vo": "cvo_stereo", "mono": "trianflow"}
#: Simulated seeds per drive: the statistics are their mean.
SEEDS = (1, 2, 3, 4)
#: How far outside the real range (as a share of its ends) a simulated figure may lie (issue 22).
RANGE_SLACK = 0.30


@dataclass(frozen=True)
class StatRow:
    """One drive's statistics: KITTI t_err (%) and r_err (deg/100 m), |yaw drift| (deg/100 m),
    scale σ per 100 m window, |start scale bias|, lateral RMSE (m). A metric preset's t_err is
    scored as written; a monocular one after one fitted scale, as KITTI scores monocular results."""

    drive: str
    source: str  # "real" or the preset and weather, e.g. "vo clear"
    t_err_percent: float
    r_err_deg_per_100m: float
    yaw_drift_deg_per_100m: float
    scale_window_sigma: float
    start_scale_bias: float
    lateral_rmse_m: float


def _row(drive: str, source: str, stats, t_err_metric: float | None) -> StatRow:
    return StatRow(drive, source, float(t_err_metric if t_err_metric is not None else stats.kitti_t_err_percent),
                   float(stats.kitti_r_err_deg_per_100m), abs(stats.yaw_drift_deg_per_100m), stats.scale_window_sigma,
                   abs(stats.start_scale_bias or 0.0), stats.lateral_rmse_m)


def real_stats(data: str | Path, preset: str) -> list[StatRow]:
    """The statistics of the real output the preset is fitted on, drive by drive."""
    from mapfusion.metrics import kitti_errors, odometry_stats
    from mapfusion.replay import OdometryFormat, OdometryFrame, read_odometry

    d = Path(data)
    rows = []
    for drive in DRIVES:
        times = d / "kitti" / drive / "times.txt"
        t, gt = read_odometry(d / "kitti" / drive / "poses.txt", OdometryFormat.kitti, times, OdometryFrame.camera)
        _, od = read_odometry(d / "vo" / f"{REAL_METHOD[preset]}_{drive}.txt", OdometryFormat.kitti, times,
                              OdometryFrame.camera)
        metric = kitti_errors(gt, od).t_err_percent if preset != "mono" else None
        rows.append(_row(drive, "real", odometry_stats(t, gt, od), metric))
    return rows


def kitti_truth(data: str | Path, drive: str):
    """The KITTI drive's truth as the sensor models read it (in its map's ENU frame)."""
    from mapfusion.roadmap import RoadMap
    from sim.recorded import load_recorded
    from sim.scenario import Scenario

    d = Path(data) / "kitti" / drive
    sc = Scenario(map=str(d / "map.osm"), truth=str(d), duration_s=86400.0)
    return load_recorded(sc.truth, sc, RoadMap.from_osm(sc.map)).truth


def simulated_stats(data: str | Path, preset: str, weather: str = "clear", seeds: tuple[int, ...] = SEEDS,
                    overrides: dict | None = None) -> list[StatRow]:
    """The preset's statistics on each development drive's truth, the mean over ``seeds``."""
    from mapfusion.metrics import kitti_errors, odometry_stats
    from sim.sensors import odometry_preset, simulate_odometry, truth_poses

    p = dataclasses.replace(odometry_preset(preset, weather), **(overrides or {}))
    rows = []
    for drive in DRIVES:
        truth = kitti_truth(data, drive)
        per_seed = []
        for seed in seeds:
            out = simulate_odometry(truth, p, np.random.default_rng(seed), rain=weather != "clear")
            gt = truth_poses(truth)[out.frame_index]
            metric = kitti_errors(gt, out.poses).t_err_percent if preset != "mono" else None
            per_seed.append(_row(drive, f"{preset} {weather}", odometry_stats(out.t_s, gt, out.poses), metric))
        mean = {f.name: float(np.mean([getattr(r, f.name) for r in per_seed]))
                for f in dataclasses.fields(StatRow) if f.name not in ("drive", "source")}
        rows.append(StatRow(drive, f"{preset} {weather}", **mean))
    return rows


def within_real_range(sim: list[StatRow], real: list[StatRow], field: str, slack: float = RANGE_SLACK) -> list[str]:
    """The drives whose simulated ``field`` lies outside [min real · (1 − slack), max real · (1 + slack)]
    (empty: all inside)."""
    vals = [getattr(r, field) for r in real]
    lo, hi = min(vals) * (1.0 - slack), max(vals) * (1.0 + slack)
    return [f"{r.drive}: {getattr(r, field):.3g} outside [{lo:.3g}, {hi:.3g}]" for r in sim
            if not lo <= getattr(r, field) <= hi]


def verdict(row: dict) -> str | None:
    """"better" or "worse": Map-Fusion's ATE against the same engine without the map (None: failed)."""
    if "error" in row or row.get("ate_mapfusion_m") is None:
        return None
    return "better" if row["ate_mapfusion_m"] < row["ate_odometry_m"] else "worse"


def verdict_pairs(sim_rows: list[dict], real_rows: list[dict]) -> list[tuple[str, str, str | None, str | None]]:
    """(drive, preset, verdict on the simulated odometry, verdict on the real output) per pair: the
    simulated verdict is that of the mean ATE over the preset's seeds on the drive, with and without
    the map."""
    out = []
    for drive in DRIVES:
        for preset, method in REAL_METHOD.items():
            real = [r for r in real_rows if f"{method}_{drive}" in r["scenario"]]
            sims = [r for r in sim_rows if f"-{drive}-{preset}-" in r["scenario"] and verdict(r) is not None]
            sim_v = (None if not sims else verdict({"ate_mapfusion_m": np.mean([r["ate_mapfusion_m"] for r in sims]),
                                                     "ate_odometry_m": np.mean([r["ate_odometry_m"] for r in sims])}))
            out.append((drive, preset, sim_v, verdict(real[0]) if real else None))
    return out


def format_stats(rows: list[StatRow]) -> list[str]:
    """Aligned text lines, a row per drive and source."""
    head = f"{'drive':>5} {'source':>14} {'t_err %':>8} {'r_err':>6} {'|drift|':>7} {'win σ':>6} {'|start|':>7} {'lat m':>6}"
    return [head] + [f"{r.drive:>5} {r.source:>14} {r.t_err_percent:8.2f} {r.r_err_deg_per_100m:6.2f} "
                     f"{r.yaw_drift_deg_per_100m:7.2f} {r.scale_window_sigma:6.3f} {r.start_scale_bias:7.3f} "
                     f"{r.lateral_rmse_m:6.1f}" for r in rows]
