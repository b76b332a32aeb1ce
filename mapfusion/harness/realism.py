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

from .results import Estimator, ate_key, finished

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


def _stats_row(drive: str, source: str, preset: str, t_s: np.ndarray, gt: np.ndarray, od: np.ndarray) -> StatRow:
    """The statistics of odometry poses ``od`` against time-associated truth poses ``gt``: a metric
    preset's t_err as written, a monocular one's after one fitted scale (as KITTI scores them)."""
    from mapfusion.metrics import kitti_errors, odometry_stats

    stats = odometry_stats(t_s, gt, od)
    t_err = stats.kitti_t_err_percent if preset == "mono" else kitti_errors(gt, od).t_err_percent
    return StatRow(drive, source, float(t_err), float(stats.kitti_r_err_deg_per_100m),
                   abs(stats.yaw_drift_deg_per_100m), stats.scale_window_sigma, abs(stats.start_scale_bias or 0.0),
                   stats.lateral_rmse_m)


def real_stats(data: str | Path, preset: str) -> list[StatRow]:
    """The statistics of the real output the preset is fitted on, drive by drive."""
    from mapfusion.replay import OdometryFormat, OdometryFrame, read_odometry

    d = Path(data)
    rows = []
    for drive in DRIVES:
        times = d / "kitti" / drive / "times.txt"
        t, gt = read_odometry(d / "kitti" / drive / "poses.txt", OdometryFormat.kitti, times, OdometryFrame.camera)
        _, od = read_odometry(d / "vo" / f"{REAL_METHOD[preset]}_{drive}.txt", OdometryFormat.kitti, times,
                              OdometryFrame.camera)
        rows.append(_stats_row(drive, "real", preset, t, gt, od))
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
    from sim.sensors import odometry_preset, simulate_odometry, truth_poses

    p = dataclasses.replace(odometry_preset(preset, weather), **(overrides or {}))
    rows = []
    for drive in DRIVES:
        truth = kitti_truth(data, drive)
        poses = truth_poses(truth)
        per_seed = []
        for seed in seeds:
            out = simulate_odometry(truth, p, np.random.default_rng(seed), rain=weather != "clear")
            per_seed.append(_stats_row(drive, f"{preset} {weather}", preset, out.t_s, poses[out.frame_index],
                                       out.poses))
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


def _better(ate_odometry_m: float, ate_mapfusion_m: float) -> str:
    return "better" if ate_mapfusion_m < ate_odometry_m else "worse"


def verdict(row: dict) -> str | None:
    """"better" or "worse": Map-Fusion's ATE against the same engine without the map (None: failed)."""
    return _better(row[ate_key(Estimator.odometry)], row[ate_key(Estimator.mapfusion)]) if finished(row) else None


def verdict_pairs(sim_rows: list[dict], real_rows: list[dict]) -> list[tuple[str, str, str | None, str | None]]:
    """(drive, preset, verdict on the simulated odometry, verdict on the real output) per pair: the
    simulated verdict is that of the mean ATE over the preset's seeds on the drive, with and without
    the map."""
    out = []
    for drive in DRIVES:
        for preset, method in REAL_METHOD.items():
            real = [r for r in real_rows if f"{method}_{drive}" in r["scenario"]]
            sims = [r for r in sim_rows if f"-{drive}-{preset}-" in r["scenario"] and finished(r)]
            sim_v = (_better(float(np.mean([r[ate_key(Estimator.odometry)] for r in sims])),
                             float(np.mean([r[ate_key(Estimator.mapfusion)] for r in sims]))) if sims else None)
            out.append((drive, preset, sim_v, verdict(real[0]) if real else None))
    return out


def format_stats(rows: list[StatRow]) -> list[str]:
    """Aligned text lines, a row per drive and source."""
    head = (f"{'drive':>5} {'source':>14} {'t_err %':>8} {'r_err':>6} {'|drift|':>7} {'win σ':>6} {'|start|':>7} "
            f"{'lat m':>6}")
    return [head] + [f"{r.drive:>5} {r.source:>14} {r.t_err_percent:8.2f} {r.r_err_deg_per_100m:6.2f} "
                     f"{r.yaw_drift_deg_per_100m:7.2f} {r.scale_window_sigma:6.3f} {r.start_scale_bias:7.3f} "
                     f"{r.lateral_rmse_m:6.1f}" for r in rows]
